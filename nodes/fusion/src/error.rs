//! The one error type of the fusion library: every way a tile, a parameter or a canvas request
//! can be refused, each with a message that names the field, what was found and what was
//! expected.

/// `Result` with [`FusionError`].
pub type Result<T, E = FusionError> = std::result::Result<T, E>;

/// Why a panorama could not be created or a tile could not be placed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FusionError {
    /// A numeric parameter (pitch, blend ramp, ...) is out of its domain.
    #[error(transparent)]
    Param(#[from] surfstream_core::ParamError),

    /// A position, offset or plane coefficient of a tile is NaN or infinite.
    #[error("tile {index}: {field} = {value}: expected a finite number")]
    NonFinite {
        index: u32,
        field: &'static str,
        value: f64,
    },

    /// A height is +/-infinity: only NaN may mark a missing sample, so this is corrupt input.
    #[error(
        "tile {index}: heights[{row}][{col}] = {value}: expected a finite height or NaN \
         (not measured)"
    )]
    InfiniteHeight {
        index: u32,
        row: usize,
        col: usize,
        value: f32,
    },

    /// A tile position lies so far from the first tile that it cannot be a real scan position
    /// (usually a unit mix-up: mm or nm given as um).
    #[error(
        "tile {index}: {field} = {value} um is {offset_px:.3e} px from the first tile: expected \
         a scan position within {max_px:.1e} px"
    )]
    PositionOutOfRange {
        index: u32,
        field: &'static str,
        value: f64,
        offset_px: f64,
        max_px: f64,
    },

    /// The same tile index was placed twice: its heights would be counted twice.
    #[error("tile {index}: already placed (expected each tile index once per panorama)")]
    DuplicateTile { index: u32 },

    /// Placing the tile would grow the canvas beyond the configured limit.
    #[error(
        "tile {index}: the canvas would grow to {height} rows x {width} cols px, more than the limit of \
         {max_px} px (check the tile positions, or raise Panorama::set_max_canvas_px)"
    )]
    CanvasTooLarge {
        index: u32,
        width: usize,
        height: usize,
        max_px: usize,
    },

    /// `render` was given no tile: there is no panorama to render.
    #[error("tiles is empty: expected at least one tile to render")]
    NoTiles,

    /// Wavelet fusion of a tile's overlap failed (the DWT refused the overlap raster).
    #[error("tile {index}: wavelet fusion of the overlap failed: {message}")]
    WaveletFusion { index: u32, message: String },

    /// The spill file of the chunked panorama or of the kept tiles could not be created,
    /// written or read (disk full, spill folder not writable).
    #[error("spill to disk failed: {message}")]
    Spill { message: String },
}

impl From<surfstream_core::store::StoreError> for FusionError {
    /// The store's message names the spill folder and what failed.
    fn from(e: surfstream_core::store::StoreError) -> Self {
        FusionError::Spill {
            message: e.to_string(),
        }
    }
}
