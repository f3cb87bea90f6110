//! surfstream-io: files in and out: instrument height-map formats ([`formats`]), NumPy arrays
//! ([`npy`]), PNG previews ([`preview`]), the figures' shared drawing helpers ([`figure`]) and MCAP
//! recordings ([`recording`]).

pub mod figure;
pub mod formats;
pub mod input;
pub mod npy;
pub mod output;
pub mod prep;
pub mod preview;
pub mod recording;
pub mod sidecar;
pub mod tiff;
pub mod truth;
