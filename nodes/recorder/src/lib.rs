//! surfstream-recorder: records the channels wired to it into one MCAP file
//! (see `surfstream_io::recording` for the layout), finished atomically when every input
//! has ended, so a recording on disk is always complete.
//!
//! [`RecordingSession`] owns the file, the channels and the decision to finish; `node` is the
//! process shell that maps the graph's messages to it.
//!
//! Not for: reading recordings back (surfstream-io's `recording` reads them, the replay node
//! replays them) or choosing what is recorded (the graph's wiring does).

pub mod node;
pub mod ports;
pub mod session;

pub use session::RecordingSession;
