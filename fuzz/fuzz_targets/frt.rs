#![no_main]
//! Any byte string given to the Frt reader returns Ok or Err, never panics or aborts.

use libfuzzer_sys::fuzz_target;
use surfstream_io::formats::{parse_surface, Format};

fuzz_target!(|data: &[u8]| {
    if let Ok(s) = parse_surface(data, Format::Frt) {
        assert_eq!(s.heights_um.len(), s.width * s.height);
    }
});
