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

#[test]
#[cfg_attr(
    debug_assertions,
    ignore = "mcap 0.26 panics on it where overflow checks are on (debug builds): an upstream bug; release builds refuse it"
)]
fn a_chunk_record_longer_than_its_chunk_is_refused_not_panicked_on() {
    // A record inside a chunk claims more bytes than the chunk has left: mcap 0.26's linear
    // reader subtracts past zero (a panic where overflow checks are on, a wrap where not).
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/mcap-chunk-length-underflow.mcap");
    let e = match surfstream_io::recording::read_recording(&path) {
        Ok(r) => panic!(
            "read {} messages from a corrupt recording",
            r.messages.len()
        ),
        Err(e) => format!("{e:#}"),
    };
    assert!(e.contains("mcap-chunk-length-underflow.mcap"), "{e}");
}
