//! The `.bt` reader on arbitrary bytes: it may reject them, never crash; what it
//! accepts must write back and read again.
#![no_main]
use earcore_core::octree::{OcTree, OccupancyParams};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(tree) = OcTree::read_binary_bytes(data, OccupancyParams::default()) {
        let again = OcTree::read_binary_bytes(&tree.write_binary_bytes(), OccupancyParams::default())
            .expect("a tree we wrote must read back");
        assert_eq!(again.num_leaf_nodes() > 0, tree.num_leaf_nodes() > 0);
    }
});
