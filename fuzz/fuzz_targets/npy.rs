#![no_main]
//! Any byte string saved as a .npy file is read as Ok or Err, never a panic or abort.
//! The .npy reader reads from a path, so each input goes through a file in /dev/shm (or the
//! temp dir).

use libfuzzer_sys::fuzz_target;
use surfstream_io::formats::read_surface;

fuzz_target!(|data: &[u8]| {
    let dir = if std::path::Path::new("/dev/shm").is_dir() {
        std::path::PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let path = dir.join(format!("surfstream-fuzz-{}.npy", std::process::id()));
    std::fs::write(&path, data).expect("temp file writable");
    if let Ok(s) = read_surface(&path) {
        assert_eq!(s.heights_um.len(), s.width * s.height);
    }
});
