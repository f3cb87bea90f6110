//! Seeded, order-independent random streams.
//!
//! Every random quantity is drawn from its own ChaCha8 stream keyed by (seed, domain) and
//! selected by an index (a tile index, a spectrum column, ...). Streams therefore do not depend
//! on the order in which tiles or rows are processed, nor on the number of threads.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Domains: one per kind of random quantity, so that switching one degradation off does not
/// move the random numbers of another.
pub(crate) mod domain {
    /// Roughness spectrum phases, indexed by spectrum column.
    pub const ROUGHNESS: u64 = 1;
    /// Waviness components (index 0).
    pub const WAVINESS: u64 = 2;
    /// Stage error, piston and tilt, indexed by tile.
    pub const TILE_POSE: u64 = 3;
    /// Measurement noise, indexed by tile.
    pub const TILE_NOISE: u64 = 4;
    /// Isolated dropout pixels, indexed by tile.
    pub const TILE_DROPOUT: u64 = 5;
    /// Dropout blobs, indexed by tile.
    pub const TILE_BLOBS: u64 = 6;
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The random stream for (seed, domain, index).
pub(crate) fn stream(seed: u64, domain: u64, index: u64) -> ChaCha8Rng {
    let mut state = seed ^ domain.wrapping_mul(0xD6E8_FEB8_6659_FD93);
    let mut key = [0u8; 32];
    for chunk in key.chunks_exact_mut(8) {
        chunk.copy_from_slice(&splitmix64(&mut state).to_le_bytes());
    }
    let mut rng = ChaCha8Rng::from_seed(key);
    rng.set_stream(index);
    rng
}
