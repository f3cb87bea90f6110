//! MCAP inputs the fuzzer found (`fuzz/`, target `mcap`), kept as regression fixtures: each is
//! refused with an error naming the file, never a panic.

use std::path::Path;

#[test]
fn an_attachment_shorter_than_its_header_is_refused_not_panicked_on() {
    // A recording whose attachment record's body ends inside its own header: mcap 0.26's
    // record parser slices past the end ("slice index starts at 32 but ends at 30").
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mcap-short-attachment.mcap");
    let e = match surfstream_io::recording::read_recording(&path) {
        Ok(r) => panic!(
            "read {} messages from a corrupt recording",
            r.messages.len()
        ),
        Err(e) => format!("{e:#}"),
    };
    assert!(e.contains("mcap-short-attachment.mcap"), "{e}");
}
