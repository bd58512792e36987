//! Per-(object, step) storage laid out for the particle filter: object-major,
//! so one object's whole sequence is one contiguous slice.

use serde::{Deserialize, Serialize};

/// At most one value per (object, step), stored object-major: the cells of
/// object `i` are `cells[i * steps .. (i + 1) * steps]`, indexed by step.
///
/// Used for box detections, ground-truth states and ground-truth actions; a
/// `None` cell means "no row" (no detection, or unknown truth).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepTable<T> {
    steps: usize,
    cells: Vec<Option<T>>,
}

impl<T> StepTable<T> {
    /// An empty table (every cell `None`) for `objects` objects and `steps` steps.
    pub fn new(objects: usize, steps: usize) -> Self {
        StepTable { steps, cells: (0..objects * steps).map(|_| None).collect() }
    }

    /// Number of steps per object.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Number of objects.
    pub fn objects(&self) -> usize {
        self.cells.len().checked_div(self.steps).unwrap_or(0)
    }

    /// The cell of `object` at step `t`.
    ///
    /// # Panics
    /// If `object` or `t` is out of range (a programmer error).
    #[track_caller]
    pub fn get(&self, object: usize, t: usize) -> Option<&T> {
        assert!(t < self.steps, "StepTable::get: step {t} out of range 0..{}", self.steps);
        self.object(object)[t].as_ref()
    }

    /// All steps of one object, indexed by step.
    ///
    /// # Panics
    /// If `object` is out of range (a programmer error).
    #[track_caller]
    pub fn object(&self, object: usize) -> &[Option<T>] {
        let n = self.objects();
        assert!(object < n, "StepTable::object: object {object} out of range 0..{n}");
        &self.cells[object * self.steps..(object + 1) * self.steps]
    }

    /// Number of cells that hold a value.
    pub fn count(&self) -> usize {
        self.cells.iter().filter(|c| c.is_some()).count()
    }

    /// True if every cell holds a value.
    pub fn is_complete(&self) -> bool {
        self.cells.iter().all(Option::is_some)
    }

    /// Every filled cell as `(object, t, value)`, object-major.
    pub fn iter(&self) -> impl Iterator<Item = (usize, usize, &T)> + '_ {
        let steps = self.steps;
        self.cells.iter().enumerate().filter_map(move |(k, c)| c.as_ref().map(|v| (k / steps, k % steps, v)))
    }

    /// Sets a cell; returns the previous value.
    pub(crate) fn set(&mut self, object: usize, t: usize, value: T) -> Option<T> {
        self.cells[object * self.steps + t].replace(value)
    }

    /// Keeps only the rows of the listed objects, in that order.
    pub(crate) fn select(&self, objects: &[usize]) -> Self
    where
        T: Clone,
    {
        let mut cells = Vec::with_capacity(objects.len() * self.steps);
        for &o in objects {
            cells.extend_from_slice(self.object(o));
        }
        StepTable { steps: self.steps, cells }
    }
}

/// A set of 2-D points (world frame, metres) per (object, step), possibly empty,
/// stored as one flat array with offsets.
///
/// The points of `object` at step `t` are `xy[offsets[k]..offsets[k + 1]]` with
/// `k = object * steps + t`; the points of one object over all its steps are one
/// contiguous slice. Within a cell, points keep the order of the file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointSets {
    steps: usize,
    offsets: Vec<usize>,
    xy: Vec<[f64; 2]>,
}

impl PointSets {
    /// Builds the sets from `(object, t, [x, y])` triples with a counting sort
    /// (stable: points of one cell keep their input order).
    pub(crate) fn from_triples(
        objects: usize,
        steps: usize,
        triples: impl Iterator<Item = (usize, usize, [f64; 2])> + Clone,
    ) -> Self {
        let cells = objects * steps;
        let mut offsets = vec![0usize; cells + 1];
        for (o, t, _) in triples.clone() {
            offsets[o * steps + t + 1] += 1;
        }
        for k in 0..cells {
            offsets[k + 1] += offsets[k];
        }
        let mut next = offsets.clone();
        let mut xy = vec![[0.0; 2]; offsets[cells]];
        for (o, t, p) in triples {
            let k = o * steps + t;
            xy[next[k]] = p;
            next[k] += 1;
        }
        PointSets { steps, offsets, xy }
    }

    /// Number of steps per object.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Number of objects.
    pub fn objects(&self) -> usize {
        (self.offsets.len() - 1).checked_div(self.steps).unwrap_or(0)
    }

    /// The points of `object` at step `t` (possibly none).
    ///
    /// # Panics
    /// If `object` or `t` is out of range (a programmer error).
    #[track_caller]
    pub fn get(&self, object: usize, t: usize) -> &[[f64; 2]] {
        let n = self.objects();
        assert!(
            object < n && t < self.steps,
            "PointSets::get: (object {object}, step {t}) out of range ({n} objects, {} steps)",
            self.steps
        );
        let k = object * self.steps + t;
        &self.xy[self.offsets[k]..self.offsets[k + 1]]
    }

    /// The `steps + 1` offsets of one object's cells into [`PointSets::xy`]:
    /// step `t` holds `xy()[o[t]..o[t + 1]]`.
    #[track_caller]
    pub fn object_offsets(&self, object: usize) -> &[usize] {
        let n = self.objects();
        assert!(object < n, "PointSets::object_offsets: object {object} out of range 0..{n}");
        &self.offsets[object * self.steps..(object + 1) * self.steps + 1]
    }

    /// All points of all objects and steps, object-major then step-major.
    pub fn xy(&self) -> &[[f64; 2]] {
        &self.xy
    }

    /// Total number of points.
    pub fn len(&self) -> usize {
        self.xy.len()
    }

    /// True if there are no points at all.
    pub fn is_empty(&self) -> bool {
        self.xy.is_empty()
    }

    /// Every point as `(object, t, [x, y])`, object-major, then step, then file order.
    pub fn iter(&self) -> impl Iterator<Item = (usize, usize, [f64; 2])> + '_ {
        let steps = self.steps;
        self.offsets
            .windows(2)
            .enumerate()
            .flat_map(move |(k, w)| self.xy[w[0]..w[1]].iter().map(move |p| (k / steps, k % steps, *p)))
    }

    /// Keeps only the listed objects, in that order.
    pub(crate) fn select(&self, objects: &[usize]) -> Self {
        let mut offsets = Vec::with_capacity(objects.len() * self.steps + 1);
        let mut xy = Vec::new();
        offsets.push(0);
        for &o in objects {
            for t in 0..self.steps {
                xy.extend_from_slice(self.get(o, t));
                offsets.push(xy.len());
            }
        }
        PointSets { steps: self.steps, offsets, xy }
    }
}
