//! `KeyVolume`: a set of cells, each marked free and/or occupied, stored as 8×8×8
//! bricks of bits. Rays mark their cells here (dedup for ~1 ns per cell instead of a
//! hash insert per cell); reading the bricks in Morton order yields the cells sorted
//! exactly as the tree update wants them.
//!
//! Storage: when the scan's bounding box is small (any depth camera), every brick of
//! the box is allocated up front and a cell's bit is found with three table lookups
//! (`X[x] + Y[y] + Z[z]`); cells outside the box, or all cells of a huge box, go to
//! bricks found through a hash map.

use rustc_hash::FxHashMap;

use super::key::OcTreeKey;
use super::ray::RayCells;
use super::walk_avx2::{self, CellBytes};

const BRICK_WORDS: usize = 8; // 512 cells / 64 bits
/// Most bricks a dense box may hold (8 MiB per kind of mark).
const MAX_DENSE_BRICKS: usize = 1 << 17;

/// Morton code of three bits, x lowest.
const SPREAD3: [u32; 8] = [0o0, 0o1, 0o10, 0o11, 0o100, 0o101, 0o110, 0o111];

#[derive(Clone, Copy, Debug)]
struct BrickBits<'a> {
    free: &'a [u64],
    occupied: &'a [u64],
}

/// Every brick of a box, laid out brick after brick, each brick in local Morton order.
#[derive(Clone, Debug)]
struct Dense {
    /// Lowest key of the box (a multiple of 8 on every axis).
    lo: [u16; 3],
    /// Box size in cells (multiples of 8).
    dims: [usize; 3],
    /// Per-axis bit offsets; a cell's bit is `tables[0][x] + tables[1][y] + tables[2][z]`.
    tables: [Vec<u32>; 3],
    free: Vec<u64>,
    occupied: Vec<u64>,
    /// Free cells marked by the batched walk, not yet folded into `free`.
    walked: Option<CellBytes>,
}

impl Dense {
    fn new(lo: OcTreeKey, hi: OcTreeKey) -> Option<Self> {
        let lo = lo.0.map(|k| k & !7);
        let dims = [0, 1, 2].map(|a| usize::from((hi.0[a] | 7) - lo[a]) + 1);
        let bricks = [0, 1, 2].map(|a| dims[a] / 8);
        let n = bricks.iter().product::<usize>();
        if n > MAX_DENSE_BRICKS {
            return None;
        }
        let stride = [512, 512 * bricks[0], 512 * bricks[0] * bricks[1]];
        let tables = [0, 1, 2].map(|a| {
            (0..dims[a])
                .map(|c| ((c / 8) * stride[a]) as u32 + (SPREAD3[c % 8] << a))
                .collect::<Vec<u32>>()
        });
        Some(Dense {
            lo,
            dims,
            tables,
            free: vec![0; n * BRICK_WORDS],
            occupied: vec![0; n * BRICK_WORDS],
            walked: None,
        })
    }

    #[inline(always)]
    fn bit(&self, key: OcTreeKey) -> Option<usize> {
        let x = key.0[0].wrapping_sub(self.lo[0]) as usize;
        let y = key.0[1].wrapping_sub(self.lo[1]) as usize;
        let z = key.0[2].wrapping_sub(self.lo[2]) as usize;
        if x < self.dims[0] && y < self.dims[1] && z < self.dims[2] {
            Some((self.tables[0][x] + self.tables[1][y] + self.tables[2][z]) as usize)
        } else {
            None
        }
    }

    /// OR the batched walk's cell bytes into the free bits, brick by brick.
    fn fold_walked(&mut self) {
        let Some(walked) = self.walked.take() else {
            return;
        };
        // x's low two bits go to bits 0, 1, 8, 9 of a word, its third bit to the next word.
        const X4: [u64; 16] = {
            let mut t = [0u64; 16];
            let mut v = 0;
            while v < 16 {
                t[v] = (v as u64 & 1)
                    | ((v as u64 >> 1 & 1) << 1)
                    | ((v as u64 >> 2 & 1) << 8)
                    | ((v as u64 >> 3 & 1) << 9);
                v += 1;
            }
            t
        };
        let [nx, ny, nz] = self.dims;
        let (bx, by) = (nx / 8, ny / 8);
        for z in 0..nz {
            for y in 0..ny {
                let row = (z * ny + y) * nx;
                // Morton offset of (y, z) inside the brick: a word and a shift.
                let off = ((SPREAD3[y % 8] << 1) | (SPREAD3[z % 8] << 2)) as usize;
                let brick_yz = (y / 8) * bx + (z / 8) * bx * by;
                for (b, chunk) in walked.bytes[row..row + nx].chunks_exact(8).enumerate() {
                    let eight = u64::from_le_bytes(chunk.try_into().unwrap_or([0; 8]));
                    if eight == 0 {
                        continue;
                    }
                    // One bit per non-zero byte, x order.
                    let mut bits = 0usize;
                    for (x, &v) in chunk.iter().enumerate() {
                        bits |= usize::from(v != 0) << x;
                    }
                    let word = (brick_yz + b) * BRICK_WORDS + (off >> 6);
                    self.free[word] |= X4[bits & 15] << (off & 63);
                    self.free[word + 1] |= X4[bits >> 4] << (off & 63);
                }
            }
        }
    }

    fn same_box(&self, other: &Dense) -> bool {
        self.lo == other.lo && self.dims == other.dims
    }

    /// (brick Morton code, bits) of every non-empty brick.
    fn bricks(&self) -> impl Iterator<Item = (u64, BrickBits<'_>)> {
        let nb = [self.dims[0] / 8, self.dims[1] / 8];
        let base = self.lo.map(|k| k >> 3);
        (0..self.free.len() / BRICK_WORDS).filter_map(move |s| {
            let w = s * BRICK_WORDS..(s + 1) * BRICK_WORDS;
            let bits = BrickBits {
                free: &self.free[w.clone()],
                occupied: &self.occupied[w],
            };
            if bits.free.iter().chain(bits.occupied).all(|&x| x == 0) {
                return None;
            }
            let rel = [s % nb[0], (s / nb[0]) % nb[1], s / (nb[0] * nb[1])];
            let coords = [0, 1, 2].map(|a| base[a] + rel[a] as u16);
            Some((OcTreeKey(coords).morton(), bits))
        })
    }
}

#[derive(Clone, Debug)]
struct Brick {
    coords: [u16; 3],
    free: [u64; BRICK_WORDS],
    occupied: [u64; BRICK_WORDS],
}

/// Bricks allocated on demand, found by hashing their coordinates.
#[derive(Clone, Debug, Default)]
struct Sparse {
    index: FxHashMap<[u16; 3], u32>,
    bricks: Vec<Brick>,
    /// The brick of the last mark: rays stay in one brick for several cells.
    cached: Option<([u16; 3], u32)>,
}

impl Sparse {
    #[inline]
    fn brick_mut(&mut self, key: OcTreeKey) -> &mut Brick {
        let b = key.0.map(|k| k >> 3);
        let i = match self.cached {
            Some((c, i)) if c == b => i,
            _ => {
                let next = self.bricks.len() as u32;
                let i = *self.index.entry(b).or_insert(next);
                if i == next {
                    self.bricks.push(Brick {
                        coords: b,
                        free: [0; BRICK_WORDS],
                        occupied: [0; BRICK_WORDS],
                    });
                }
                self.cached = Some((b, i));
                i
            }
        };
        &mut self.bricks[i as usize]
    }

    fn find(&self, key: OcTreeKey) -> Option<&Brick> {
        self.index
            .get(&key.0.map(|k| k >> 3))
            .map(|&i| &self.bricks[i as usize])
    }
}

#[inline(always)]
fn local_index(key: OcTreeKey) -> usize {
    (SPREAD3[(key.0[0] & 7) as usize]
        | (SPREAD3[(key.0[1] & 7) as usize] << 1)
        | (SPREAD3[(key.0[2] & 7) as usize] << 2)) as usize
}

/// A set of cells marked free or occupied during one scan, dense (a bit grid) inside
/// its bounds and sparse outside; occupied wins over free.
#[derive(Clone, Debug, Default)]
pub struct KeyVolume {
    dense: Option<Dense>,
    sparse: Sparse,
}

impl KeyVolume {
    /// An empty volume for cells anywhere.
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty volume expecting cells within the key box `[lo, hi]` (others still work).
    pub fn with_bounds(lo: OcTreeKey, hi: OcTreeKey) -> Self {
        KeyVolume {
            dense: Dense::new(lo, hi),
            sparse: Sparse::default(),
        }
    }

    /// Mark a cell free (seen through by a ray).
    #[inline(always)]
    pub fn mark_free(&mut self, key: OcTreeKey) {
        match self.dense.as_mut().and_then(|d| d.bit(key).map(|i| (d, i))) {
            Some((d, i)) => d.free[i >> 6] |= 1 << (i & 63),
            None => self.mark_sparse(key, false),
        }
    }

    /// Mark a cell occupied (a ray's end cell).
    #[inline(always)]
    pub fn mark_occupied(&mut self, key: OcTreeKey) {
        match self.dense.as_mut().and_then(|d| d.bit(key).map(|i| (d, i))) {
            Some((d, i)) => d.occupied[i >> 6] |= 1 << (i & 63),
            None => self.mark_sparse(key, true),
        }
    }

    /// Mark many cells occupied (the dense box looked up once, not per cell).
    pub fn mark_all_occupied(&mut self, keys: impl IntoIterator<Item = OcTreeKey>) {
        let mut outside = Vec::new();
        match self.dense.as_mut() {
            Some(d) => {
                // Neighbouring points often share a cell: its bit is set once.
                let mut last = None;
                for key in keys {
                    if last == Some(key) {
                        continue;
                    }
                    last = Some(key);
                    match d.bit(key) {
                        Some(i) => d.occupied[i >> 6] |= 1 << (i & 63),
                        None => outside.push(key),
                    }
                }
            }
            None => outside.extend(keys),
        }
        for key in outside {
            self.mark_sparse(key, true);
        }
    }

    /// The slow path, out of line so the dense path inlines into the ray loop.
    #[cold]
    #[inline(never)]
    fn mark_sparse(&mut self, key: OcTreeKey, occupied: bool) {
        let l = local_index(key);
        let b = self.sparse.brick_mut(key);
        let words = if occupied {
            &mut b.occupied
        } else {
            &mut b.free
        };
        words[l >> 6] |= 1 << (l & 63);
    }

    /// Direct access to the dense box for the hot ray loop, when there is one: its
    /// `mark_free` has no slow path (a call inside the loop makes the compiler keep the
    /// ray's state in memory, halving the speed), so it reports keys it cannot hold.
    #[inline(always)]
    pub fn dense_marker(&mut self) -> Option<DenseMarker<'_>> {
        self.dense.as_mut().map(|dense| DenseMarker {
            dense,
            offsets: [0; 3],
            outside: false,
        })
    }

    /// Walk the rays from `origin` to `ends` (keys in `end_keys`) and mark their cells
    /// free with the batched walk ([`walk_avx2`]) when this CPU and the dense box allow
    /// it. Returns the indices of the rays left for the scalar walk (all of them
    /// without a batched walk or a dense box). Call [`KeyVolume::settle`] before
    /// reading the volume.
    pub(crate) fn walk_rays(
        &mut self,
        conv: &super::key::KeyConverter,
        origin: super::ray::Point3f,
        ends: &[super::ray::Point3f],
        end_keys: &[Option<OcTreeKey>],
    ) -> Vec<usize> {
        match self.dense.as_mut() {
            // A byte per cell of the dense box (at most 64 Mi, as many bytes a thread,
            // zeroed lazily: only the pages rays cross are touched); folding it costs
            // one pass over the box, far less than the scalar walk it replaces.
            Some(d) if walk_avx2::available() => {
                let (lo, dims) = (d.lo, d.dims);
                let walked = d.walked.get_or_insert_with(|| CellBytes::new(lo, dims));
                walk_avx2::walk_rays(conv, origin, ends, end_keys, walked)
            }
            _ => (0..ends.len()).collect(),
        }
    }

    /// Fold what the batched walk marked into the volume's bits.
    pub(crate) fn settle(&mut self) {
        if let Some(d) = self.dense.as_mut() {
            d.fold_walked();
        }
    }

    fn settled(&self) -> bool {
        self.dense.as_ref().is_none_or(|d| d.walked.is_none())
    }

    /// Whether `key` is marked free and not occupied.
    pub fn is_free(&self, key: OcTreeKey) -> bool {
        debug_assert!(self.settled(), "settle() the volume before reading it");
        let test = |free: u64, occ: u64, i: usize| ((free & !occ) >> (i & 63)) & 1 == 1;
        if let Some(d) = &self.dense {
            if let Some(i) = d.bit(key) {
                return test(d.free[i >> 6], d.occupied[i >> 6], i);
            }
        }
        let l = local_index(key);
        self.sparse
            .find(key)
            .is_some_and(|b| test(b.free[l >> 6], b.occupied[l >> 6], l))
    }

    /// Union with another volume (the per-thread volumes of a parallel scan).
    pub fn merge(mut self, mut other: KeyVolume) -> KeyVolume {
        self.settle();
        other.settle();
        let KeyVolume {
            dense: other_dense,
            sparse: other_sparse,
        } = other;
        if let Some(od) = other_dense {
            match &mut self.dense {
                Some(d) if d.same_box(&od) => {
                    for (a, b) in d.free.iter_mut().zip(&od.free) {
                        *a |= b;
                    }
                    for (a, b) in d.occupied.iter_mut().zip(&od.occupied) {
                        *a |= b;
                    }
                }
                _ => {
                    for (code, bits) in od.bricks() {
                        self.or_brick(code, bits.free, bits.occupied);
                    }
                }
            }
        }
        for b in other_sparse.bricks {
            self.or_brick(OcTreeKey(b.coords).morton(), &b.free, &b.occupied);
        }
        self
    }

    /// OR a whole brick in, cell by cell (only used when merging unlike volumes).
    fn or_brick(&mut self, code: u64, free: &[u64], occupied: &[u64]) {
        for l in 0..512u64 {
            let (w, bit) = ((l >> 6) as usize, l & 63);
            let key = OcTreeKey::from_morton((code << 9) | l);
            if (free[w] >> bit) & 1 == 1 {
                self.mark_free(key);
            }
            if (occupied[w] >> bit) & 1 == 1 {
                self.mark_occupied(key);
            }
        }
    }

    /// Visit every marked cell in Morton order as (code, occupied); a cell marked both
    /// free and occupied is reported once, as occupied.
    pub fn for_each_sorted(&self, mut f: impl FnMut(u64, bool)) {
        debug_assert!(self.settled(), "settle() the volume before reading it");
        let mut bricks: Vec<(u64, BrickBits<'_>)> = Vec::new();
        if let Some(d) = &self.dense {
            bricks.extend(d.bricks());
        }
        bricks.extend(self.sparse.bricks.iter().map(|b| {
            (
                OcTreeKey(b.coords).morton(),
                BrickBits {
                    free: &b.free,
                    occupied: &b.occupied,
                },
            )
        }));
        bricks.sort_unstable_by_key(|&(code, _)| code);
        // A brick can be in both stores only after merging unlike volumes; those
        // duplicates are adjacent after sorting and are combined here.
        let mut i = 0;
        while i < bricks.len() {
            let code = bricks[i].0;
            let mut free = [0u64; BRICK_WORDS];
            let mut occupied = [0u64; BRICK_WORDS];
            while i < bricks.len() && bricks[i].0 == code {
                for w in 0..BRICK_WORDS {
                    free[w] |= bricks[i].1.free[w];
                    occupied[w] |= bricks[i].1.occupied[w];
                }
                i += 1;
            }
            let base = code << 9;
            for w in 0..BRICK_WORDS {
                let mut bits = free[w] | occupied[w];
                while bits != 0 {
                    let t = bits.trailing_zeros() as u64;
                    bits &= bits - 1;
                    f(base | ((w as u64) << 6) | t, (occupied[w] >> t) & 1 == 1);
                }
            }
        }
    }

    /// At least as many as the cells `for_each_sorted` visits (exact unless unlike
    /// volumes were merged), counted by bits: for reserving room for them.
    pub fn marked_bound(&self) -> usize {
        let ones = |free: &[u64], occupied: &[u64]| -> usize {
            free.iter()
                .zip(occupied)
                .map(|(f, o)| (f | o).count_ones() as usize)
                .sum()
        };
        let dense = self
            .dense
            .as_ref()
            .map_or(0, |d| ones(&d.free, &d.occupied));
        dense
            + self
                .sparse
                .bricks
                .iter()
                .map(|b| ones(&b.free, &b.occupied))
                .sum::<usize>()
    }

    /// Counts of (free-only, occupied) cells.
    pub fn counts(&self) -> (usize, usize) {
        let (mut free, mut occ) = (0, 0);
        self.for_each_sorted(|_, o| if o { occ += 1 } else { free += 1 });
        (free, occ)
    }
}

/// See [`KeyVolume::dense_marker`]. As a [`RayCells`] receiver it keeps each axis's
/// bit offset and refreshes only the axis that moved (one table load per cell).
pub struct DenseMarker<'a> {
    dense: &'a mut Dense,
    offsets: [u32; 3],
    /// A cell fell outside the box (nothing was marked for it).
    pub outside: bool,
}

impl DenseMarker<'_> {
    #[inline(always)]
    fn offset(&self, axis: usize, k: u16) -> Option<u32> {
        self.dense.tables[axis]
            .get(usize::from(k.wrapping_sub(self.dense.lo[axis])))
            .copied()
    }
}

impl RayCells for DenseMarker<'_> {
    #[inline(always)]
    fn cell(&mut self, key: OcTreeKey, moved: usize) {
        // `moved` is a constant at each call site once inlined, so this match folds away.
        let ok = match moved {
            0 => self
                .offset(0, key.0[0])
                .map(|o| self.offsets[0] = o)
                .is_some(),
            1 => self
                .offset(1, key.0[1])
                .map(|o| self.offsets[1] = o)
                .is_some(),
            2 => self
                .offset(2, key.0[2])
                .map(|o| self.offsets[2] = o)
                .is_some(),
            _ => match (
                self.offset(0, key.0[0]),
                self.offset(1, key.0[1]),
                self.offset(2, key.0[2]),
            ) {
                (Some(x), Some(y), Some(z)) => {
                    self.offsets = [x, y, z];
                    true
                }
                _ => false,
            },
        };
        if ok {
            let i = (self.offsets[0] + self.offsets[1] + self.offsets[2]) as usize;
            // In range by construction of the tables; `get_mut` keeps it panic-free.
            if let Some(w) = self.dense.free.get_mut(i >> 6) {
                *w |= 1 << (i & 63);
            }
        } else {
            self.outside = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(mut v: KeyVolume, mut w: KeyVolume) {
        let keys = [
            OcTreeKey([9, 3, 700]),
            OcTreeKey([1, 2, 3]),
            OcTreeKey([65535, 0, 8]),
            OcTreeKey([8, 8, 8]),
        ];
        for k in keys {
            v.mark_free(k);
        }
        v.mark_occupied(keys[1]);
        w.mark_occupied(OcTreeKey([4, 4, 4]));
        w.mark_free(keys[0]);
        let v = v.merge(w);
        let mut out = Vec::new();
        v.for_each_sorted(|m, occ| out.push((m, occ)));
        let mut expected: Vec<(u64, bool)> =
            keys.iter().map(|k| (k.morton(), *k == keys[1])).collect();
        expected.push((OcTreeKey([4, 4, 4]).morton(), true));
        expected.sort();
        assert_eq!(out, expected);
        assert_eq!(v.counts(), (3, 2));
        assert!(v.is_free(keys[0]) && !v.is_free(keys[1]) && !v.is_free(OcTreeKey([5, 5, 5])));
    }

    #[test]
    fn cells_come_out_sorted_and_occupied_wins() {
        check(KeyVolume::new(), KeyVolume::new());
        // Dense boxes covering only some of the cells: the rest go to the sparse store.
        let (lo, hi) = (OcTreeKey([0, 0, 0]), OcTreeKey([20, 20, 20]));
        check(
            KeyVolume::with_bounds(lo, hi),
            KeyVolume::with_bounds(lo, hi),
        );
        check(KeyVolume::with_bounds(lo, hi), KeyVolume::new());
        check(
            KeyVolume::new(),
            KeyVolume::with_bounds(OcTreeKey([3, 1, 600]), OcTreeKey([30, 9, 800])),
        );
    }
}
