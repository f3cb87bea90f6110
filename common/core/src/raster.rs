//! The one raster type: a row-major grid of `rows x cols` samples, rows along y, columns
//! along x (DESIGN §2: "row index grows with y").
//!
//! Every crate names a raster's dimensions the same way, `rows` and `cols`, so a non-square
//! map cannot be transposed silently by mixing `(width, height)` with `(rows, cols)`.
//! [`Raster`] owns its samples, [`RasterView`] borrows them (a frame payload in shared memory,
//! a slice of a larger buffer). The element type is the caller's: `f32` for frames, `f64` for
//! metrology and absolute heights.

use serde::{Deserialize, Serialize};

/// The size of a raster: `rows` along y, `cols` along x.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub struct Shape {
    pub rows: usize,
    pub cols: usize,
}

impl Shape {
    pub const fn new(rows: usize, cols: usize) -> Self {
        Self { rows, cols }
    }
    /// Number of samples, `None` on overflow (a size claimed by a file, say).
    pub fn checked_len(self) -> Option<usize> {
        self.rows.checked_mul(self.cols)
    }
    /// Number of samples (`rows * cols`); saturates instead of overflowing.
    pub fn len(self) -> usize {
        self.rows.saturating_mul(self.cols)
    }
    pub fn is_empty(self) -> bool {
        self.rows == 0 || self.cols == 0
    }
    /// Row-major index of (row, col).
    #[inline]
    pub fn index(self, row: usize, col: usize) -> usize {
        row * self.cols + col
    }
    /// Errors unless `found` samples fill this shape and it has at least one row and column.
    pub fn check(self, found: usize) -> Result<(), ShapeError> {
        check(self, found)
    }
    /// The pixel centre, (col, row), of a raster of this shape: the pivot of tilts.
    #[inline]
    pub fn centre_px(self) -> (f64, f64) {
        (
            (self.cols as f64 - 1.0) * 0.5,
            (self.rows as f64 - 1.0) * 0.5,
        )
    }
}

impl std::fmt::Display for Shape {
    /// `rows x cols`, the one order used in every message.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} x {}", self.rows, self.cols)
    }
}

/// Why samples and a shape do not make a raster: the one shape error, which the crates' errors
/// wrap (serde: a registration's rejection carries it into the matcher's report).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error, Serialize, Deserialize)]
pub enum ShapeError {
    #[error("a {shape} (rows x cols) raster needs {expected} samples, found {found}")]
    Length {
        shape: Shape,
        expected: usize,
        found: usize,
    },
    #[error("a raster needs at least one row and one column, got {0} (rows x cols)")]
    Empty(Shape),
}

fn check(shape: Shape, found: usize) -> Result<(), ShapeError> {
    if shape.is_empty() {
        return Err(ShapeError::Empty(shape));
    }
    match shape.checked_len() {
        Some(expected) if expected == found => Ok(()),
        _ => Err(ShapeError::Length {
            shape,
            expected: shape.len(),
            found,
        }),
    }
}

/// An owned row-major raster.
#[derive(Debug, Clone, PartialEq)]
pub struct Raster<T> {
    values: Vec<T>,
    shape: Shape,
}

/// A borrowed row-major raster.
#[derive(Debug, PartialEq)]
pub struct RasterView<'a, T> {
    values: &'a [T],
    shape: Shape,
}

impl<T> Clone for RasterView<'_, T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for RasterView<'_, T> {}

impl<T> Raster<T> {
    /// Wraps row-major samples; errors unless `values.len() == rows * cols` and both are > 0.
    pub fn new(values: Vec<T>, shape: Shape) -> Result<Self, ShapeError> {
        check(shape, values.len())?;
        Ok(Self { values, shape })
    }
    /// A raster of one value.
    pub fn filled(shape: Shape, value: T) -> Self
    where
        T: Clone,
    {
        Self {
            values: vec![value; shape.len()],
            shape,
        }
    }
    pub fn shape(&self) -> Shape {
        self.shape
    }
    pub fn rows(&self) -> usize {
        self.shape.rows
    }
    pub fn cols(&self) -> usize {
        self.shape.cols
    }
    pub fn values(&self) -> &[T] {
        &self.values
    }
    pub fn values_mut(&mut self) -> &mut [T] {
        &mut self.values
    }
    pub fn into_values(self) -> Vec<T> {
        self.values
    }
    pub fn view(&self) -> RasterView<'_, T> {
        RasterView {
            values: &self.values,
            shape: self.shape,
        }
    }
    pub fn row(&self, row: usize) -> &[T] {
        self.view().row(row)
    }
    pub fn row_mut(&mut self, row: usize) -> &mut [T] {
        let cols = self.shape.cols;
        &mut self.values[row * cols..(row + 1) * cols]
    }
    /// Rows in order, each `cols` long.
    pub fn rows_iter(&self) -> std::slice::ChunksExact<'_, T> {
        self.view().rows_iter()
    }
    pub fn rows_iter_mut(&mut self) -> std::slice::ChunksExactMut<'_, T> {
        self.values.chunks_exact_mut(self.shape.cols.max(1))
    }
    #[inline]
    pub fn get(&self, row: usize, col: usize) -> Option<&T> {
        self.view().get(row, col)
    }
    /// A raster of `f` applied to every sample.
    pub fn map<U>(&self, f: impl FnMut(&T) -> U) -> Raster<U> {
        self.view().map(f)
    }
}

impl<'a, T> RasterView<'a, T> {
    /// Borrows row-major samples; errors unless `values.len() == rows * cols` and both are > 0.
    pub fn new(values: &'a [T], shape: Shape) -> Result<Self, ShapeError> {
        check(shape, values.len())?;
        Ok(Self { values, shape })
    }
    pub fn shape(&self) -> Shape {
        self.shape
    }
    pub fn rows(&self) -> usize {
        self.shape.rows
    }
    pub fn cols(&self) -> usize {
        self.shape.cols
    }
    pub fn values(&self) -> &'a [T] {
        self.values
    }
    pub fn row(&self, row: usize) -> &'a [T] {
        &self.values[row * self.shape.cols..(row + 1) * self.shape.cols]
    }
    pub fn rows_iter(&self) -> std::slice::ChunksExact<'a, T> {
        self.values.chunks_exact(self.shape.cols.max(1))
    }
    #[inline]
    pub fn get(&self, row: usize, col: usize) -> Option<&'a T> {
        (row < self.shape.rows && col < self.shape.cols)
            .then(|| &self.values[self.shape.index(row, col)])
    }
    pub fn to_owned(&self) -> Raster<T>
    where
        T: Clone,
    {
        Raster {
            values: self.values.to_vec(),
            shape: self.shape,
        }
    }
    pub fn map<U>(&self, f: impl FnMut(&T) -> U) -> Raster<U> {
        Raster {
            values: self.values.iter().map(f).collect(),
            shape: self.shape,
        }
    }
}

impl Raster<f32> {
    /// Widens to f64 (metrology, absolute heights).
    pub fn to_f64(&self) -> Raster<f64> {
        self.map(|&v| v as f64)
    }
}

impl Raster<f64> {
    /// Narrows to f32 (frame payloads).
    pub fn to_f32(&self) -> Raster<f32> {
        self.map(|&v| v as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_and_cols_are_not_interchangeable() {
        // 2 rows x 3 cols: row 1 is [3, 4, 5].
        let r = Raster::new((0..6).map(|v| v as f32).collect(), Shape::new(2, 3)).unwrap();
        assert_eq!(r.row(1), &[3.0, 4.0, 5.0]);
        assert_eq!(r.get(1, 2), Some(&5.0));
        assert_eq!(r.get(2, 0), None);
        assert_eq!(r.shape().to_string(), "2 x 3");
        assert_eq!(r.shape().centre_px(), (1.0, 0.5));
    }

    #[test]
    fn a_wrong_length_or_empty_shape_is_refused() {
        assert!(matches!(
            Raster::new(vec![0.0f32; 5], Shape::new(2, 3)),
            Err(ShapeError::Length {
                expected: 6,
                found: 5,
                ..
            })
        ));
        assert!(matches!(
            RasterView::<f32>::new(&[], Shape::new(0, 3)),
            Err(ShapeError::Empty(_))
        ));
        let huge = Shape::new(usize::MAX, 2);
        assert_eq!(huge.checked_len(), None);
        assert!(Raster::new(vec![0u8; 4], huge).is_err());
    }
}
