//! OctoMap's two file formats, readable and writable both ways:
//! `.bt` (binary: 2 bits per child, maximum-likelihood occupancy only) and
//! `.ot` (full: a float log-odds and a child byte per node, depth first).
//!
//! Readers take untrusted bytes: every length, depth and value is checked and
//! failures return `Error::Format`, never a panic.

use super::arena::NONE;
use super::key::TREE_DEPTH;
use super::occupancy::{OcTree, OccupancyParams};
use crate::error::{Error, Result};

const BINARY_HEADER: &str = "# Octomap OcTree binary file";
const FULL_HEADER: &str = "# Octomap OcTree file";
const TREE_TYPE: &str = "OcTree";

/// Maximum-likelihood class of a node when writing `.bt`.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Class {
    Free,
    Occupied,
    Inner,
}

fn header(first_line: &str, size: usize, resolution: f64) -> String {
    format!(
        "{first_line}\n# (feel free to add / change comments, but leave the first line as it is!)\n#\nid {TREE_TYPE}\nsize {size}\nres {resolution}\ndata\n"
    )
}

struct Header {
    id: String,
    size: usize,
    resolution: f64,
}

/// Parse the text header up to and including the `data` line (OctoMap's `readHeader`);
/// returns the header and the offset of the first data byte.
fn parse_header(bytes: &[u8], first_line: &str) -> Result<(Header, usize)> {
    let line_end = |from: usize| {
        bytes[from..]
            .iter()
            .position(|&b| b == b'\n')
            .map(|i| from + i)
    };
    let first_end = line_end(0).ok_or_else(|| Error::Format("missing header line".into()))?;
    let first = String::from_utf8_lossy(&bytes[..first_end]);
    if !first.starts_with(first_line) {
        return Err(Error::Format(format!(
            "first line must start with {first_line:?}, found {:?}",
            truncate(&first)
        )));
    }
    let mut pos = first_end + 1;
    let (mut id, mut size, mut resolution) = (None, None, None);
    loop {
        let end = line_end(pos)
            .ok_or_else(|| Error::Format("header ends before the 'data' line".into()))?;
        let line = std::str::from_utf8(&bytes[pos..end])
            .map_err(|_| Error::Format("header is not text".into()))?
            .trim();
        pos = end + 1;
        let mut words = line.split_whitespace();
        match words.next() {
            Some("data") => break,
            Some(w) if w.starts_with('#') => {}
            Some("id") => id = words.next().map(str::to_owned),
            Some("size") => {
                size = Some(
                    words
                        .next()
                        .and_then(|s| s.parse::<usize>().ok())
                        .ok_or_else(|| Error::Format(format!("bad size line {line:?}")))?,
                )
            }
            Some("res") => {
                resolution = Some(
                    words
                        .next()
                        .and_then(|s| s.parse::<f64>().ok())
                        .ok_or_else(|| Error::Format(format!("bad res line {line:?}")))?,
                )
            }
            // OctoMap skips unknown keywords and blank lines too.
            _ => {}
        }
    }
    let id = id.ok_or_else(|| Error::Format("header has no 'id'".into()))?;
    let size = size.ok_or_else(|| Error::Format("header has no 'size'".into()))?;
    let resolution = resolution.ok_or_else(|| Error::Format("header has no 'res'".into()))?;
    super::key::check_resolution(resolution).map_err(|e| Error::Format(e.to_string()))?;
    Ok((
        Header {
            id,
            size,
            resolution,
        },
        pos,
    ))
}

fn truncate(s: &str) -> String {
    s.chars().take(60).collect()
}

/// A cursor over the data section that fails cleanly at the end.
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    pub(crate) fn take<const N: usize>(&mut self) -> Result<[u8; N]> {
        let end = self.pos + N;
        let chunk = self.bytes.get(self.pos..end).ok_or_else(|| {
            Error::Format(format!(
                "data ends early (byte {} of {})",
                self.pos,
                self.bytes.len()
            ))
        })?;
        self.pos = end;
        Ok(chunk.try_into().expect("slice length is N"))
    }

    /// The tree's data must end the file. OctoMap's readers stop after the tree and
    /// never look further, but neither writer puts anything there: bytes after the
    /// tree are a second tree, a concatenation or corruption, not part of this map.
    fn finish(&self) -> Result<()> {
        match self.bytes.len() - self.pos.min(self.bytes.len()) {
            0 => Ok(()),
            extra => Err(Error::Format(format!(
                "{extra} bytes after the tree's data (a map file holds one tree and ends with it)"
            ))),
        }
    }
}

/// First line of [`OcTree::write_state_bytes`]' format.
const STATE_HEADER: &[u8] = b"earcore OcTree state 1\n";

impl OcTree {
    /// Everything the tree holds, for pickling: the `.ot` file (nodes and log-odds)
    /// preceded by what `.ot` does not store, the sensor model and the danger state
    /// (parameters, dangerous voxels, the open frame's hits and free sightings, the
    /// last frame's obstacles). [`read_state_bytes`](Self::read_state_bytes) gives an
    /// equal tree back.
    pub fn write_state_bytes(&self) -> Vec<u8> {
        let mut out = STATE_HEADER.to_vec();
        let p = self.params();
        for v in [
            p.prob_hit,
            p.prob_miss,
            p.clamping_min,
            p.clamping_max,
            p.occupancy_threshold,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        self.danger.write_state(&mut out);
        out.extend_from_slice(&self.write_full_bytes());
        out
    }

    /// Parse what [`write_state_bytes`](Self::write_state_bytes) wrote; untrusted
    /// bytes are checked as for the map files.
    pub fn read_state_bytes(bytes: &[u8]) -> Result<OcTree> {
        let rest = bytes.strip_prefix(STATE_HEADER).ok_or_else(|| {
            Error::Format("not an earcore OcTree state (wrong first line)".into())
        })?;
        let mut r = Reader {
            bytes: rest,
            pos: 0,
        };
        let mut value = || r.take::<8>().map(f64::from_le_bytes);
        let params = OccupancyParams {
            prob_hit: value()?,
            prob_miss: value()?,
            clamping_min: value()?,
            clamping_max: value()?,
            occupancy_threshold: value()?,
        };
        params
            .validate()
            .map_err(|e| Error::Format(format!("sensor model: {e}")))?;
        let danger = super::danger::DangerMap::read_state(&mut r)?;
        let mut tree = OcTree::read_full_bytes(&rest[r.pos..], params)?;
        tree.danger = danger;
        Ok(tree)
    }

    /// Serialise as OctoMap's `.bt`. The tree is not modified: the maximum-likelihood
    /// pruning that OctoMap's `writeBinary` applies in place is computed on the side.
    pub fn write_binary_bytes(&self) -> Vec<u8> {
        if self.root == NONE {
            return header(BINARY_HEADER, 0, self.resolution()).into_bytes();
        }
        let class = self.max_likelihood_classes();
        let size = self.count_written(self.root, &class);
        let mut out = header(BINARY_HEADER, size, self.resolution()).into_bytes();
        self.write_binary_node(self.root, &class, &mut out);
        out
    }

    /// Classes after OctoMap's `toMaxLikelihood(); prune();` — pruning depth by depth
    /// from the bottom and stopping at the first depth where nothing collapsed.
    fn max_likelihood_classes(&self) -> Vec<Class> {
        let mut class = vec![Class::Inner; self.arena_slots()];
        let mut inner_by_depth: Vec<Vec<u32>> = vec![Vec::new(); TREE_DEPTH as usize + 1];
        let mut stack = vec![(self.root, 0u32)];
        while let Some((n, d)) = stack.pop() {
            if self.arena.has_children(n) {
                inner_by_depth[d as usize].push(n);
                for c in self.arena.children(n) {
                    if c != NONE {
                        stack.push((c, d + 1));
                    }
                }
            } else {
                class[n as usize] = if self.is_occupied_log_odds(self.arena.value(n)) {
                    Class::Occupied
                } else {
                    Class::Free
                };
            }
        }
        for depth in (1..TREE_DEPTH as usize).rev() {
            let mut pruned = 0;
            for &n in &inner_by_depth[depth] {
                let children = self.arena.children(n);
                let first = if children[0] == NONE {
                    Class::Inner
                } else {
                    class[children[0] as usize]
                };
                if first != Class::Inner
                    && children
                        .iter()
                        .all(|&c| c != NONE && class[c as usize] == first)
                {
                    class[n as usize] = first;
                    pruned += 1;
                }
            }
            if pruned == 0 {
                break;
            }
        }
        class
    }

    fn arena_slots(&self) -> usize {
        let mut max = 0u32;
        let mut stack = vec![self.root];
        while let Some(n) = stack.pop() {
            max = max.max(n);
            stack.extend(self.arena.children(n).into_iter().filter(|&c| c != NONE));
        }
        max as usize + 1
    }

    fn count_written(&self, n: u32, class: &[Class]) -> usize {
        let mut count = 1;
        if class[n as usize] == Class::Inner || n == self.root {
            for c in self.arena.children(n) {
                if c != NONE {
                    count += if class[c as usize] == Class::Inner {
                        self.count_written(c, class)
                    } else {
                        1
                    };
                }
            }
        }
        count
    }

    fn write_binary_node(&self, n: u32, class: &[Class], out: &mut Vec<u8>) {
        let children = self.arena.children(n);
        let mut bits = [0u8; 2];
        for (i, &c) in children.iter().enumerate() {
            if c == NONE {
                continue;
            }
            let code = match class[c as usize] {
                Class::Free => 0b01,
                Class::Occupied => 0b10,
                Class::Inner => 0b11,
            };
            bits[i / 4] |= code << (2 * (i % 4));
        }
        out.extend_from_slice(&bits);
        for c in children {
            if c != NONE && class[c as usize] == Class::Inner {
                self.write_binary_node(c, class, out);
            }
        }
    }

    /// Parse OctoMap's `.bt`: occupied leaves get the upper clamping bound, free ones the
    /// lower, inner nodes the maximum of their children (the root: the upper bound).
    pub fn read_binary_bytes(bytes: &[u8], params: OccupancyParams) -> Result<OcTree> {
        let (head, start) = parse_header(bytes, BINARY_HEADER)?;
        let mut tree = OcTree::with_params(head.resolution, params)?;
        let mut r = Reader { bytes, pos: start };
        if head.size > 0 {
            tree.root = tree.arena.alloc(tree.lo.clamp_max);
            tree.read_binary_node(tree.root, 0, &mut r)?;
        }
        r.finish()?;
        tree.arena.trim_spare();
        if tree.size() != head.size {
            return Err(Error::Format(format!(
                "header says {} nodes, data holds {}",
                head.size,
                tree.size()
            )));
        }
        Ok(tree)
    }

    fn read_binary_node(&mut self, node: u32, depth: u32, r: &mut Reader) -> Result<()> {
        let bits = r.take::<2>()?;
        if depth >= TREE_DEPTH && bits != [0, 0] {
            return Err(Error::Format(format!(
                "nodes nested deeper than {TREE_DEPTH} levels"
            )));
        }
        let mut inner = Vec::new();
        for i in 0..8 {
            match (bits[i / 4] >> (2 * (i % 4))) & 0b11 {
                0b01 => {
                    self.arena.create_child(node, i, self.lo.clamp_min);
                }
                0b10 => {
                    self.arena.create_child(node, i, self.lo.clamp_max);
                }
                0b11 => inner.push(self.arena.create_child(node, i, self.lo.clamp_max)),
                _ => {}
            }
        }
        for c in inner {
            self.read_binary_node(c, depth + 1, r)?;
            if !self.arena.has_children(c) {
                return Err(Error::Format(
                    "a node marked as inner has no children".into(),
                ));
            }
            let max = self.max_child_log_odds(c);
            self.arena.set_value(c, max);
        }
        Ok(())
    }

    /// Serialise as OctoMap's `.ot` (every node's log-odds, nothing lost).
    pub fn write_full_bytes(&self) -> Vec<u8> {
        let mut out = header(FULL_HEADER, self.size(), self.resolution()).into_bytes();
        if self.root != NONE {
            let mut stack = vec![self.root];
            while let Some(n) = stack.pop() {
                out.extend_from_slice(&self.arena.value(n).to_le_bytes());
                let children = self.arena.children(n);
                let mut mask = 0u8;
                for (i, &c) in children.iter().enumerate() {
                    if c != NONE {
                        mask |= 1 << i;
                    }
                }
                out.push(mask);
                // Depth first, child 0 first: push in reverse.
                stack.extend(children.iter().rev().filter(|&&c| c != NONE));
            }
        }
        out
    }

    /// Parse OctoMap's `.ot` (only the plain `OcTree` type).
    pub fn read_full_bytes(bytes: &[u8], params: OccupancyParams) -> Result<OcTree> {
        let (head, start) = parse_header(bytes, FULL_HEADER)?;
        if head.id != TREE_TYPE {
            return Err(Error::Format(format!(
                "tree type {:?} is not supported, only {TREE_TYPE:?}",
                head.id
            )));
        }
        let mut tree = OcTree::with_params(head.resolution, params)?;
        let mut r = Reader { bytes, pos: start };
        if head.size > 0 {
            tree.root = tree.arena.alloc(0.0);
            // (node, depth) in the order the file lists them.
            let mut stack = vec![(tree.root, 0u32)];
            while let Some((n, depth)) = stack.pop() {
                let value = f32::from_le_bytes(r.take::<4>()?);
                if !value.is_finite() {
                    return Err(Error::Format(format!(
                        "node log-odds {value} is not finite"
                    )));
                }
                tree.arena.set_value(n, value);
                let [mask] = r.take::<1>()?;
                if mask != 0 && depth >= TREE_DEPTH {
                    return Err(Error::Format(format!(
                        "nodes nested deeper than {TREE_DEPTH} levels"
                    )));
                }
                let mut created = Vec::new();
                for i in 0..8 {
                    if mask & (1 << i) != 0 {
                        created.push(tree.arena.create_child(n, i, 0.0));
                    }
                }
                stack.extend(created.into_iter().rev().map(|c| (c, depth + 1)));
            }
        }
        r.finish()?;
        tree.arena.trim_spare();
        if tree.size() != head.size {
            return Err(Error::Format(format!(
                "header says {} nodes, data holds {}",
                head.size,
                tree.size()
            )));
        }
        Ok(tree)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small_tree() -> OcTree {
        let mut tree = OcTree::new(0.1).unwrap();
        let points = [[1.0, 0.5, 0.25], [-0.7, 0.3, 1.1], [0.2, -0.9, 0.4]];
        tree.insert_point_cloud(&points, [0.0; 3], None, false)
            .unwrap();
        tree
    }

    #[test]
    fn bytes_after_the_tree_are_refused() {
        let tree = small_tree();
        let params = OccupancyParams::default();
        let bt = tree.write_binary_bytes();
        let ot = tree.write_full_bytes();
        let empty_bt = OcTree::new(0.1).unwrap().write_binary_bytes();
        let empty_ot = OcTree::new(0.1).unwrap().write_full_bytes();
        type Reader = fn(&[u8], OccupancyParams) -> Result<OcTree>;
        let readers: [(&[u8], Reader); 4] = [
            (&bt, OcTree::read_binary_bytes),
            (&ot, OcTree::read_full_bytes),
            (&empty_bt, OcTree::read_binary_bytes),
            (&empty_ot, OcTree::read_full_bytes),
        ];
        for (bytes, read) in readers {
            // The file as written reads back to the same bytes.
            assert!(read(bytes, params).is_ok());
            // One stray byte, a newline, or a second copy of the whole file.
            for tail in [&[0u8][..], b"\n", bytes] {
                let mut longer = bytes.to_vec();
                longer.extend_from_slice(tail);
                match read(&longer, params) {
                    Err(Error::Format(msg)) => {
                        assert!(
                            msg.contains(&format!("{} bytes after", tail.len())),
                            "{msg}"
                        )
                    }
                    other => panic!("{} trailing bytes gave {other:?}", tail.len()),
                }
            }
        }
    }

    #[test]
    fn state_bytes_round_trip_and_refuse_damage() {
        let mut tree = OcTree::with_params(
            0.1,
            OccupancyParams {
                prob_hit: 0.8,
                ..OccupancyParams::default()
            },
        )
        .unwrap();
        let scan = [[1.0, 0.5, 0.25], [-0.7, 0.3, 1.1], [0.2, -0.9, 0.4]];
        tree.insert_point_cloud(&scan, [0.0; 3], None, false)
            .unwrap();
        tree.danger_map_mut().end_frame(0.1).unwrap();
        tree.insert_point_cloud(&scan[..1], [0.0, 0.0, 0.1], None, false)
            .unwrap();
        let bytes = tree.write_state_bytes();
        let back = OcTree::read_state_bytes(&bytes).unwrap();
        assert_eq!(back.write_full_bytes(), tree.write_full_bytes());
        assert_eq!(back.params(), tree.params());
        let (d0, d1) = (tree.danger_map(), back.danger_map());
        assert_eq!(d0.sorted_cells(), d1.sorted_cells());
        assert_eq!(d0.current_obstacles(), d1.current_obstacles());
        assert_eq!(d0.params(), d1.params());
        // The open frame (hits, free sightings) continues the same way.
        let (mut a, mut b) = (tree.clone(), back);
        let ra = a.danger_map_mut().end_frame(0.2).unwrap();
        let rb = b.danger_map_mut().end_frame(0.2).unwrap();
        assert_eq!(ra, rb);
        assert_eq!(a.danger_map().sorted_cells(), b.danger_map().sorted_cells());
        // Every truncation and a trailing byte are format errors, never a panic.
        for cut in 0..bytes.len() {
            assert!(matches!(
                OcTree::read_state_bytes(&bytes[..cut]),
                Err(Error::Format(_))
            ));
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(
            OcTree::read_state_bytes(&longer),
            Err(Error::Format(_))
        ));
    }

    #[test]
    fn header_resolutions_outside_the_key_range_are_refused() {
        let ot =
            String::from_utf8_lossy(&OcTree::new(0.1).unwrap().write_full_bytes()).into_owned();
        for res in [
            "1e-100", "1e-19", "2e14", "1e308", "0", "-0.1", "inf", "nan",
        ] {
            let bytes = ot.replace("res 0.1", &format!("res {res}"));
            match OcTree::read_full_bytes(bytes.as_bytes(), OccupancyParams::default()) {
                Err(Error::Format(msg)) => assert!(msg.contains("resolution"), "{msg}"),
                other => panic!("res {res} gave {other:?}"),
            }
        }
        for res in ["1e-18", "1e14"] {
            let bytes = ot.replace("res 0.1", &format!("res {res}"));
            let tree = OcTree::read_full_bytes(bytes.as_bytes(), OccupancyParams::default());
            assert!(tree.is_ok(), "res {res}");
        }
    }
}
