//! The `.ot` reader on arbitrary bytes: it may reject them, never crash; what it
//! accepts must round-trip byte for byte.
#![no_main]
use earcore_core::octree::{OcTree, OccupancyParams};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(tree) = OcTree::read_full_bytes(data, OccupancyParams::default()) {
        let bytes = tree.write_full_bytes();
        let again = OcTree::read_full_bytes(&bytes, OccupancyParams::default()).expect("a tree we wrote must read back");
        assert_eq!(again.write_full_bytes(), bytes);
        let _ = tree.write_binary_bytes();
    }
});
