//! Node storage for octrees: one arena of nodes and one of child blocks.
//!
//! A node is 8 bytes (payload + index of its child block); an inner node owns one
//! block of eight `u32` child indices (32 bytes). No allocation per node: nodes and
//! blocks live in two `Vec`s, and freed slots go to free lists that later
//! insertions reuse. Compare OctoMap: 16 bytes per node plus 64 per inner node.

/// Marks "no node" / "no child block".
pub const NONE: u32 = u32::MAX;

#[derive(Clone, Copy, Debug)]
pub struct Node<T> {
    pub value: T,
    /// Index into the block arena, or `NONE` for a leaf.
    children: u32,
}

#[derive(Clone, Debug, Default)]
pub struct NodeArena<T> {
    nodes: Vec<Node<T>>,
    blocks: Vec<[u32; 8]>,
    free_nodes: Vec<u32>,
    free_blocks: Vec<u32>,
}

impl<T: Copy> NodeArena<T> {
    pub fn new() -> Self {
        NodeArena {
            nodes: Vec::new(),
            blocks: Vec::new(),
            free_nodes: Vec::new(),
            free_blocks: Vec::new(),
        }
    }

    /// Number of live nodes.
    #[inline]
    pub fn len(&self) -> usize {
        self.nodes.len() - self.free_nodes.len()
    }

    pub fn clear(&mut self) {
        self.nodes.clear();
        self.blocks.clear();
        self.free_nodes.clear();
        self.free_blocks.clear();
    }

    /// Bytes held by the arena, spare capacity included.
    pub fn memory_usage(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<Node<T>>()
            + self.blocks.capacity() * std::mem::size_of::<[u32; 8]>()
            + (self.free_nodes.capacity() + self.free_blocks.capacity()) * 4
    }

    /// Give back spare capacity beyond a quarter of what is in use; called after a
    /// batch of insertions, whose growth doubles.
    pub fn trim_spare(&mut self) {
        trim(&mut self.nodes);
        trim(&mut self.blocks);
    }

    #[inline]
    pub fn alloc(&mut self, value: T) -> u32 {
        let node = Node {
            value,
            children: NONE,
        };
        match self.free_nodes.pop() {
            Some(i) => {
                self.nodes[i as usize] = node;
                i
            }
            None => {
                grow(&mut self.nodes);
                self.nodes.push(node);
                (self.nodes.len() - 1) as u32
            }
        }
    }

    #[inline]
    pub fn value(&self, n: u32) -> T {
        self.nodes[n as usize].value
    }

    #[inline]
    pub fn set_value(&mut self, n: u32, value: T) {
        self.nodes[n as usize].value = value;
    }

    #[inline]
    pub fn has_children(&self, n: u32) -> bool {
        self.nodes[n as usize].children != NONE
    }

    /// Child `pos` (0..8) of `n`, if it exists.
    #[inline]
    pub fn child(&self, n: u32, pos: usize) -> Option<u32> {
        let b = self.nodes[n as usize].children;
        if b == NONE {
            return None;
        }
        let c = self.blocks[b as usize][pos];
        (c != NONE).then_some(c)
    }

    /// All eight child slots of `n` (`NONE` where absent); all `NONE` for a leaf.
    #[inline]
    pub fn children(&self, n: u32) -> [u32; 8] {
        let b = self.nodes[n as usize].children;
        if b == NONE {
            [NONE; 8]
        } else {
            self.blocks[b as usize]
        }
    }

    /// Create child `pos` of `n` holding `value`; the slot must be empty.
    pub fn create_child(&mut self, n: u32, pos: usize, value: T) -> u32 {
        let child = self.alloc(value);
        let mut b = self.nodes[n as usize].children;
        if b == NONE {
            b = match self.free_blocks.pop() {
                Some(i) => {
                    self.blocks[i as usize] = [NONE; 8];
                    i
                }
                None => {
                    grow(&mut self.blocks);
                    self.blocks.push([NONE; 8]);
                    (self.blocks.len() - 1) as u32
                }
            };
            self.nodes[n as usize].children = b;
        }
        debug_assert_eq!(self.blocks[b as usize][pos], NONE);
        self.blocks[b as usize][pos] = child;
        child
    }

    /// Give `n` eight children holding its own value (OctoMap's `expandNode`).
    pub fn expand(&mut self, n: u32) {
        debug_assert!(!self.has_children(n));
        let v = self.value(n);
        for pos in 0..8 {
            self.create_child(n, pos, v);
        }
    }

    /// Free every node below `n` and make `n` a leaf.
    pub fn delete_children(&mut self, n: u32) {
        let b = self.nodes[n as usize].children;
        if b == NONE {
            return;
        }
        let block = self.blocks[b as usize];
        for c in block {
            if c != NONE {
                self.delete_children(c);
                self.free_nodes.push(c);
            }
        }
        self.nodes[n as usize].children = NONE;
        self.free_blocks.push(b);
    }
}

/// Double when full: a batch that builds millions of nodes then copies the arena a
/// dozen times instead of forty (growing by a quarter spent 12 % of a 9 M-node
/// insertion in copies and in faulting in the fresh pages). `trim_spare` gives the
/// excess back once the batch is done.
#[inline]
fn grow<T>(v: &mut Vec<T>) {
    if v.len() == v.capacity() {
        v.reserve_exact(v.capacity().max(1024));
    }
}

/// Shrink `v` to a quarter of spare capacity above its length, if it holds more:
/// maps are long-lived and large, so spare capacity is memory held for nothing.
/// Shrinking reallocates in place (a heap chunk is split, an mmap'd one remapped).
fn trim<T>(v: &mut Vec<T>) {
    let keep = v.len() + (v.len() / 4).max(1024);
    if v.capacity() > keep {
        v.shrink_to(keep);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn freed_slots_are_reused() {
        let mut a: NodeArena<f32> = NodeArena::new();
        let root = a.alloc(0.0);
        a.expand(root);
        assert_eq!(a.len(), 9);
        a.delete_children(root);
        assert_eq!(a.len(), 1);
        assert!(!a.has_children(root));
        a.expand(root);
        let before = a.memory_usage();
        for _ in 0..100 {
            a.delete_children(root);
            a.expand(root);
        }
        assert_eq!(a.len(), 9);
        assert_eq!(
            a.memory_usage(),
            before,
            "expanding again must reuse freed slots"
        );
        assert_eq!(std::mem::size_of::<Node<f32>>(), 8);
    }

    #[test]
    fn trimming_keeps_a_quarter_spare_and_every_node() {
        let mut a: NodeArena<f32> = NodeArena::new();
        let root = a.alloc(-1.0);
        let mut parents = vec![root];
        for _ in 0..6 {
            let mut next = Vec::new();
            for &p in &parents {
                for pos in 0..8 {
                    next.push(a.create_child(p, pos, (p * 8 + pos as u32) as f32));
                }
            }
            parents = next;
        }
        let (nodes, blocks) = (a.nodes.len(), a.blocks.len());
        assert_eq!(nodes, (8usize.pow(7) - 1) / 7);
        let before: Vec<f32> = (0..nodes as u32).map(|n| a.value(n)).collect();
        a.trim_spare();
        assert!(
            a.nodes.capacity() <= nodes + nodes / 4,
            "{} spare of {nodes}",
            a.nodes.capacity() - nodes
        );
        assert!(a.blocks.capacity() <= blocks + blocks / 4);
        let after: Vec<f32> = (0..nodes as u32).map(|n| a.value(n)).collect();
        assert_eq!(before, after);
        assert_eq!(
            a.children(root)[3],
            before.iter().position(|&v| v == 3.0).unwrap() as u32
        );
    }
}
