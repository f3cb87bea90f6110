//! The one error type of the mesher: every way a height field, a parameter or a mesh can be
//! refused, each with a message that says what was found and what was expected.

/// `Result` with [`MeshError`].
pub type Result<T, E = MeshError> = std::result::Result<T, E>;

/// Why a height field could not be meshed or a mesh could not be written.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The grid is too small to enclose a volume (a solid needs at least one grid cell).
    #[error(
        "height field is {rows} x {cols} samples (rows x cols); a solid needs at least 2 x 2 \
         samples"
    )]
    TooSmall { rows: usize, cols: usize },

    /// The samples and the declared shape do not make a raster.
    #[error("height field: {0}")]
    Shape(#[from] surfstream_core::raster::ShapeError),

    /// A numeric parameter is out of its domain.
    #[error(transparent)]
    Param(#[from] surfstream_core::ParamError),

    /// Every sample is NaN: there is no surface to mesh.
    #[error("height field has no measured sample: all {samples} samples are NaN")]
    NoValidSample { samples: usize },

    /// A sample is +/-infinity: only NaN may mark a missing sample, so this is corrupt input.
    #[error(
        "height sample at row {row}, column {col} is {value}; expected a finite height in um \
         (NaN marks a missing sample)"
    )]
    InfiniteSample { row: usize, col: usize, value: f32 },

    /// The mesh would need more vertices or triangles than 32-bit indices (or STL's 32-bit
    /// triangle count) can address.
    #[error("mesh too large: {what} = {count}, the limit is {limit}")]
    TooLarge {
        what: &'static str,
        count: usize,
        limit: usize,
    },

    /// A tolerance search's coarsest mesh already needs more surface triangles than the
    /// budget (a smooth surface: the tolerance is relative to its own Sq). Typed so that a
    /// caller can give a larger budget without reading the message.
    #[error(
        "tolerance {tolerance}: even the coarsest mesh ({triangles} surface triangles) exceeds \
         max_triangles = {budget}"
    )]
    CoarsestOverBudget {
        tolerance: String,
        triangles: usize,
        budget: usize,
    },

    /// A mesh handed to a writer or to `solid::close_top_surface` is malformed.
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),

    /// Two options that cannot be combined, or an option the input cannot satisfy.
    #[error("{0}")]
    Incompatible(String),

    /// The streaming mesher's spill file (its triangles, 12 bytes each) could not be created,
    /// written or read back.
    #[error("the mesher's triangles (12 bytes each): {0}")]
    Spill(#[from] surfstream_core::store::StoreError),

    /// A report record that cannot be written as JSON.
    #[error(transparent)]
    Record(#[from] surfstream_core::record::RecordError),

    /// Writing the STL stream failed.
    #[error("writing STL: {0}")]
    Io(#[from] std::io::Error),
}
