//! MCAP recordings (in progress).
