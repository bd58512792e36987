//! The dense tensor: a shape and contiguous row-major storage, plus shape helpers
//! (broadcasting, axis decomposition) shared by the forward and backward kernels.

use serde::{Deserialize, Serialize};

use crate::float::Float;

/// A dense, row-major, n-dimensional array. A scalar has shape `[]`.
///
/// Deserialising checks that the data has as many elements as the shape says
/// (a damaged file is an error, not a tensor that panics when used).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(bound = "F: Float", try_from = "TensorParts<F>")]
pub struct Tensor<F: Float> {
    shape: Vec<usize>,
    data: Vec<F>,
}

/// A tensor's fields as serialised, before [`Tensor`]'s check of their sizes.
#[derive(Deserialize)]
#[serde(bound = "F: Float")]
struct TensorParts<F: Float> {
    shape: Vec<usize>,
    data: Vec<F>,
}

impl<F: Float> TryFrom<TensorParts<F>> for Tensor<F> {
    type Error = String;

    fn try_from(parts: TensorParts<F>) -> Result<Self, String> {
        let TensorParts { shape, data } = parts;
        let numel = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        if numel != Some(data.len()) {
            return Err(format!("tensor of shape {shape:?} with {} elements", data.len()));
        }
        Ok(Tensor { shape, data })
    }
}

impl<F: Float> Tensor<F> {
    /// Builds a tensor from a shape and row-major data.
    ///
    /// Panics if the data length does not match the shape.
    ///
    /// ```
    /// use autodiff::Tensor;
    /// let t = Tensor::new(&[2, 3], vec![1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0]);
    /// assert_eq!(t.at(&[1, 2]), 6.0);
    /// ```
    #[track_caller]
    pub fn new(shape: &[usize], data: Vec<F>) -> Self {
        let numel: usize = shape.iter().product();
        assert_eq!(numel, data.len(), "Tensor::new: shape {shape:?} needs {numel} elements, got {}", data.len());
        Tensor { shape: shape.to_vec(), data }
    }

    /// A 1-D tensor holding `data`.
    pub fn from_vec(data: Vec<F>) -> Self {
        Tensor { shape: vec![data.len()], data }
    }

    /// A 1-D tensor from f64 values (converted to `F`).
    pub fn from_f64s(shape: &[usize], data: &[f64]) -> Self {
        Self::new(shape, data.iter().map(|&x| F::from_f64(x)).collect())
    }

    /// A scalar (shape `[]`).
    pub fn scalar(x: F) -> Self {
        Tensor { shape: vec![], data: vec![x] }
    }

    /// A tensor of the given shape filled with `value`.
    pub fn full(shape: &[usize], value: F) -> Self {
        let numel = shape.iter().product();
        Tensor { shape: shape.to_vec(), data: vec![value; numel] }
    }

    /// A tensor of zeros.
    pub fn zeros(shape: &[usize]) -> Self {
        Self::full(shape, F::ZERO)
    }

    /// A tensor of ones.
    pub fn ones(shape: &[usize]) -> Self {
        Self::full(shape, F::ONE)
    }

    /// The shape.
    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// Number of dimensions.
    pub fn rank(&self) -> usize {
        self.shape.len()
    }

    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.data.len()
    }

    /// The row-major data.
    pub fn data(&self) -> &[F] {
        &self.data
    }

    /// The row-major data, mutable.
    pub fn data_mut(&mut self) -> &mut [F] {
        &mut self.data
    }

    /// Consumes the tensor, returning its data.
    pub fn into_data(self) -> Vec<F> {
        self.data
    }

    /// The single value of a one-element tensor.
    #[track_caller]
    pub fn item(&self) -> F {
        assert_eq!(self.data.len(), 1, "item: tensor of shape {:?} is not a scalar", self.shape);
        self.data[0]
    }

    /// The element at a multi-index.
    #[track_caller]
    pub fn at(&self, index: &[usize]) -> F {
        self.data[self.offset(index)]
    }

    /// Sets the element at a multi-index.
    #[track_caller]
    pub fn set(&mut self, index: &[usize], value: F) {
        let o = self.offset(index);
        self.data[o] = value;
    }

    #[track_caller]
    fn offset(&self, index: &[usize]) -> usize {
        assert_eq!(index.len(), self.shape.len(), "index {index:?} for shape {:?}", self.shape);
        let mut o = 0;
        for (&i, &d) in index.iter().zip(&self.shape) {
            assert!(i < d, "index {index:?} out of bounds for shape {:?}", self.shape);
            o = o * d + i;
        }
        o
    }

    /// The same data with another shape of equal element count.
    #[track_caller]
    pub fn reshape(mut self, shape: &[usize]) -> Self {
        let numel: usize = shape.iter().product();
        assert_eq!(numel, self.data.len(), "reshape: {:?} -> {shape:?}", self.shape);
        self.shape = shape.to_vec();
        self
    }

    /// Applies `f` to every element.
    pub fn map(&self, f: impl Fn(F) -> F) -> Self {
        Tensor { shape: self.shape.clone(), data: self.data.iter().map(|&x| f(x)).collect() }
    }

    /// Converts every element to another float type.
    pub fn cast<G: Float>(&self) -> Tensor<G> {
        Tensor { shape: self.shape.clone(), data: self.data.iter().map(|&x| G::from_f64(x.to_f64())).collect() }
    }

    /// The data as f64 values.
    pub fn to_f64_vec(&self) -> Vec<f64> {
        self.data.iter().map(|x| x.to_f64()).collect()
    }

    /// Sum of squares of all elements, accumulated in f64.
    pub fn sum_squares(&self) -> f64 {
        self.data.iter().map(|x| x.to_f64() * x.to_f64()).sum()
    }

    /// Whether every element is finite.
    pub fn all_finite(&self) -> bool {
        self.data.iter().all(|x| x.is_finite())
    }

    pub(crate) fn from_parts(shape: Vec<usize>, data: Vec<F>) -> Self {
        debug_assert_eq!(shape.iter().product::<usize>(), data.len());
        Tensor { shape, data }
    }

    pub(crate) fn into_parts(self) -> (Vec<usize>, Vec<F>) {
        (self.shape, self.data)
    }
}

/// Splits `shape` around `axis` into (outer, axis length, inner) element counts.
#[track_caller]
pub(crate) fn axis_split(shape: &[usize], axis: usize, op: &str) -> (usize, usize, usize) {
    assert!(axis < shape.len(), "{op}: axis {axis} out of range for shape {shape:?}");
    let outer = shape[..axis].iter().product();
    let inner = shape[axis + 1..].iter().product();
    (outer, shape[axis], inner)
}

/// The numpy-style broadcast of two shapes, or `None` when they are incompatible.
pub fn broadcast_shapes(a: &[usize], b: &[usize]) -> Option<Vec<usize>> {
    let rank = a.len().max(b.len());
    let mut out = vec![0; rank];
    for i in 0..rank {
        let da = if i + a.len() >= rank { a[i + a.len() - rank] } else { 1 };
        let db = if i + b.len() >= rank { b[i + b.len() - rank] } else { 1 };
        out[i] = if da == db || db == 1 {
            da
        } else if da == 1 {
            db
        } else {
            return None;
        };
    }
    Some(out)
}

/// Strides (in elements) with which an input of shape `shape` is read when broadcast
/// to `out` (right-aligned); broadcast dimensions get stride 0.
pub(crate) fn broadcast_strides(shape: &[usize], out: &[usize]) -> Vec<usize> {
    let rank = out.len();
    let mut strides = vec![0; rank];
    let mut s = 1;
    for i in (0..shape.len()).rev() {
        let o = rank - shape.len() + i;
        strides[o] = if shape[i] == 1 && out[o] != 1 { 0 } else { s };
        s *= shape[i];
    }
    strides
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broadcast_rules() {
        assert_eq!(broadcast_shapes(&[3, 1], &[4]), Some(vec![3, 4]));
        assert_eq!(broadcast_shapes(&[], &[2, 2]), Some(vec![2, 2]));
        assert_eq!(broadcast_shapes(&[2, 3], &[3, 2]), None);
        assert_eq!(broadcast_strides(&[3, 1], &[3, 4]), vec![1, 0]);
        assert_eq!(broadcast_strides(&[4], &[3, 4]), vec![0, 1]);
    }
}
