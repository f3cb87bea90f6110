//! surfstream-recorder: records the channels wired to it into one MCAP file
//! (see `surfstream_io::recording` for the layout), finished atomically when every input
//! has ended, so a recording on disk is always complete.

pub mod node;
pub mod ports;
