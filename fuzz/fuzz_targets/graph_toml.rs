#![no_main]
//! Any byte string given as a graph file (TOML, see `entry.rs`): Ok or Err, never a panic or an abort.

use libfuzzer_sys::fuzz_target;

#[path = "../entry.rs"]
mod entry;

fuzz_target!(|data: &[u8]| {
    entry::graph_toml(data);
});
