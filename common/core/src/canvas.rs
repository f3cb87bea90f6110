//! A raster that grows in any direction on a fixed grid: the panorama as the fusion blends it
//! and as the wavelet node mirrors it from patches.
//!
//! Grid index `k` along x is the pixel centred at `anchor_x_um + k * pitch_x_um` (likewise y);
//! the anchor is the first tile, so indices left of or above it are negative. A
//! [`GrowingCanvas`] holds the samples of one [`GridRect`] of that grid and grows it, keeping
//! its content, when something lands outside. Growth is amortised ([`amortised_growth`]) so the
//! work per tile does not grow with the panorama.

use crate::raster::Shape;

/// Grid indices, half-open: columns `x0 .. x1`, rows `y0 .. y1` (may be negative).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct GridRect {
    pub x0: i64,
    pub y0: i64,
    pub x1: i64,
    pub y1: i64,
}

impl GridRect {
    /// The rectangle of `shape` whose first pixel is grid pixel (x0, y0).
    pub fn at(x0: i64, y0: i64, shape: Shape) -> Self {
        Self {
            x0,
            y0,
            x1: x0 + shape.cols as i64,
            y1: y0 + shape.rows as i64,
        }
    }

    /// Columns.
    pub fn cols(&self) -> usize {
        (self.x1 - self.x0).max(0) as usize
    }

    /// Rows.
    pub fn rows(&self) -> usize {
        (self.y1 - self.y0).max(0) as usize
    }

    pub fn shape(&self) -> Shape {
        Shape::new(self.rows(), self.cols())
    }

    pub fn is_empty(&self) -> bool {
        self.x1 <= self.x0 || self.y1 <= self.y0
    }

    /// Pixel count, `None` if it does not fit in usize.
    pub fn area(&self) -> Option<usize> {
        self.cols().checked_mul(self.rows())
    }

    pub fn contains(&self, other: &GridRect) -> bool {
        other.x0 >= self.x0 && other.x1 <= self.x1 && other.y0 >= self.y0 && other.y1 <= self.y1
    }

    /// The smallest rectangle covering both.
    pub fn union(&self, other: &GridRect) -> GridRect {
        GridRect {
            x0: self.x0.min(other.x0),
            y0: self.y0.min(other.y0),
            x1: self.x1.max(other.x1),
            y1: self.y1.max(other.y1),
        }
    }

    /// The common part; `None` when they do not overlap.
    pub fn intersect(&self, other: &GridRect) -> Option<GridRect> {
        let r = GridRect {
            x0: self.x0.max(other.x0),
            y0: self.y0.max(other.y0),
            x1: self.x1.min(other.x1),
            y1: self.y1.min(other.y1),
        };
        (!r.is_empty()).then_some(r)
    }

    /// Grown by `margin` px on every side.
    pub fn expand(&self, margin: i64) -> GridRect {
        GridRect {
            x0: self.x0 - margin,
            y0: self.y0 - margin,
            x1: self.x1 + margin,
            y1: self.y1 + margin,
        }
    }

    /// The smallest rectangle of whole `block x block` cells of the grid (cells start at
    /// multiples of `block`) that covers this one: pooled patches tile seamlessly.
    pub fn align_out(&self, block: usize) -> GridRect {
        let b = block.max(1) as i64;
        let x0 = self.x0.div_euclid(b) * b;
        let y0 = self.y0.div_euclid(b) * b;
        GridRect {
            x0,
            y0,
            x1: x0 + (self.x1 - x0 + b - 1) / b * b,
            y1: y0 + (self.y1 - y0 + b - 1) / b * b,
        }
    }
}

/// Where a canvas covering `current` moves to cover `need` as well: a side that must move out
/// moves by at least `need`'s size or half the canvas, whichever is more, so n tiles
/// reallocate O(log n) times and never copy more than a constant multiple of the final canvas
/// in total. An empty `current` gives `need` itself.
pub fn amortised_growth(current: GridRect, need: GridRect) -> GridRect {
    if current.is_empty() {
        return need;
    }
    if current.contains(&need) {
        return current;
    }
    let step_x = need.cols().max(current.cols() / 2) as i64;
    let step_y = need.rows().max(current.rows() / 2) as i64;
    GridRect {
        x0: if need.x0 < current.x0 {
            need.x0.min(current.x0 - step_x)
        } else {
            current.x0
        },
        x1: if need.x1 > current.x1 {
            need.x1.max(current.x1 + step_x)
        } else {
            current.x1
        },
        y0: if need.y0 < current.y0 {
            need.y0.min(current.y0 - step_y)
        } else {
            current.y0
        },
        y1: if need.y1 > current.y1 {
            need.y1.max(current.y1 + step_y)
        } else {
            current.y1
        },
    }
}

/// The samples of one grid rectangle, row-major, that can move to a larger rectangle keeping
/// its content. Pixels never written hold the fill value (NaN for heights, 0 for weights).
#[derive(Debug, Clone)]
pub struct GrowingCanvas<T> {
    rect: GridRect,
    values: Vec<T>,
    fill: T,
}

impl<T: Copy> GrowingCanvas<T> {
    /// An empty canvas (no rectangle yet).
    pub fn new(fill: T) -> Self {
        Self {
            rect: GridRect::default(),
            values: Vec::new(),
            fill,
        }
    }

    /// The allocated rectangle (empty before the first allocation).
    pub fn rect(&self) -> GridRect {
        self.rect
    }

    /// True before the first allocation.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Samples per row of the allocation.
    pub fn stride(&self) -> usize {
        self.rect.cols()
    }

    /// All samples, row-major over [`GrowingCanvas::rect`].
    pub fn values(&self) -> &[T] {
        &self.values
    }

    pub fn values_mut(&mut self) -> &mut [T] {
        &mut self.values
    }

    /// Index into [`GrowingCanvas::values`] of grid pixel (x, y), which must lie inside.
    #[inline]
    pub fn index(&self, x: i64, y: i64) -> usize {
        (y - self.rect.y0) as usize * self.stride() + (x - self.rect.x0) as usize
    }

    /// The sample at grid pixel (x, y); `None` outside the allocation.
    pub fn get(&self, x: i64, y: i64) -> Option<T> {
        (x >= self.rect.x0 && x < self.rect.x1 && y >= self.rect.y0 && y < self.rect.y1)
            .then(|| self.values[self.index(x, y)])
    }

    /// Moves the canvas to `rect`, keeping the content of the old rectangle where they
    /// overlap (the usual case: `rect` contains the old one); new pixels get the fill value.
    /// Zero fills of plain numbers are lazy allocations: headroom costs no RAM until written.
    pub fn reallocate(&mut self, rect: GridRect) {
        let mut values = vec![self.fill; rect.area().unwrap_or(0)];
        if !self.values.is_empty() {
            if let Some(common) = self.rect.intersect(&rect) {
                let (w, ow, nw) = (common.cols(), self.rect.cols(), rect.cols());
                for y in common.y0..common.y1 {
                    let src =
                        (y - self.rect.y0) as usize * ow + (common.x0 - self.rect.x0) as usize;
                    let dst = (y - rect.y0) as usize * nw + (common.x0 - rect.x0) as usize;
                    values[dst..dst + w].copy_from_slice(&self.values[src..src + w]);
                }
            }
        }
        self.rect = rect;
        self.values = values;
    }

    /// Makes the canvas cover `need`, growing by [`amortised_growth`]; true if it moved.
    pub fn grow_to_cover(&mut self, need: GridRect) -> bool {
        if !self.is_empty() && self.rect.contains(&need) {
            return false;
        }
        let current = if self.is_empty() {
            GridRect::default()
        } else {
            self.rect
        };
        self.reallocate(amortised_growth(current, need));
        true
    }

    /// Copies row-major `values` into `rect`, growing the canvas as needed. Errors (and
    /// changes nothing) when the lengths disagree.
    pub fn write(&mut self, rect: GridRect, values: &[T]) -> Result<(), crate::ShapeError> {
        let shape = rect.shape();
        if shape.checked_len() != Some(values.len()) || shape.is_empty() {
            return Err(crate::ShapeError::Length {
                shape,
                expected: shape.len(),
                found: values.len(),
            });
        }
        self.grow_to_cover(rect);
        let w = rect.cols();
        for (y, line) in (rect.y0..rect.y1).zip(values.chunks_exact(w)) {
            let at = self.index(rect.x0, y);
            self.values[at..at + w].copy_from_slice(line);
        }
        Ok(())
    }

    /// The samples of `rect`, row-major; the fill value outside the allocation.
    pub fn read(&self, rect: GridRect) -> Vec<T> {
        let mut out = vec![self.fill; rect.area().unwrap_or(0)];
        let Some(common) = (!self.is_empty())
            .then(|| self.rect.intersect(&rect))
            .flatten()
        else {
            return out;
        };
        let (w, ow) = (common.cols(), rect.cols());
        for y in common.y0..common.y1 {
            let src = self.index(common.x0, y);
            let dst = (y - rect.y0) as usize * ow + (common.x0 - rect.x0) as usize;
            out[dst..dst + w].copy_from_slice(&self.values[src..src + w]);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rect(x0: i64, y0: i64, cols: usize, rows: usize) -> GridRect {
        GridRect::at(x0, y0, Shape::new(rows, cols))
    }

    #[test]
    fn grows_in_every_direction_and_keeps_content() {
        let mut c = GrowingCanvas::new(f32::NAN);
        c.write(rect(0, 0, 4, 3), &[1.0; 12]).unwrap();
        assert_eq!(c.rect(), rect(0, 0, 4, 3));
        for (x0, y0, v) in [(-5, 0, 2.0), (0, -4, 3.0), (6, 5, 4.0), (2, 1, 5.0)] {
            let r = rect(x0, y0, 4, 3);
            c.write(r, &[v; 12]).unwrap();
            assert_eq!(c.read(r), vec![v; 12]);
        }
        assert!(c.rect().contains(&rect(-5, -4, 15, 12)));
        // The first patch survives where nothing overwrote it; untouched pixels stay NaN.
        assert_eq!(c.read(rect(0, 0, 2, 1)), vec![1.0, 1.0]);
        assert!(c.read(rect(9, -4, 1, 1))[0].is_nan());
        // Outside the allocation reads the fill value.
        assert!(c.read(rect(1000, 1000, 1, 1))[0].is_nan());
        assert!(c.write(rect(0, 0, 2, 2), &[0.0; 3]).is_err());
    }

    #[test]
    fn growth_is_amortised() {
        let mut c = GrowingCanvas::new(0.0f32);
        let mut moves = 0;
        for k in 0..64 {
            moves += c.grow_to_cover(rect(k * 10, 0, 10, 10)) as usize;
        }
        // Each move grows by half: 1 + log1.5(64) ~ 11, not 64.
        assert!(moves <= 12, "{moves} reallocations for 64 tiles");
        assert_eq!(c.get(0, 0), Some(0.0));
        assert_eq!(c.get(-1, 0), None);
    }

    #[test]
    fn rect_algebra() {
        let a = rect(-3, 2, 5, 4);
        assert_eq!((a.cols(), a.rows()), (5, 4));
        assert_eq!(a.intersect(&rect(10, 10, 1, 1)), None);
        assert_eq!(a.intersect(&rect(0, 0, 10, 3)), Some(rect(0, 2, 2, 1)));
        assert_eq!(a.expand(2), rect(-5, 0, 9, 8));
        assert_eq!(rect(-3, 2, 5, 3).align_out(4), rect(-4, 0, 8, 8));
        assert_eq!(rect(0, 0, 4, 4).align_out(4), rect(0, 0, 4, 4));
    }
}
