//! The bridge between the CPU backends' float primitives and the host kernels: f32 slices in,
//! `Vec<f32>` out. Flex hands its storage over without a copy; ndarray (deprecated in Burn
//! 0.22.1, kept as the second CPU backend) goes through `TensorData`.

use burn::backend::Backend;
use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape, TensorData};

/// A CPU backend whose f32 tensors the host kernels can read and write.
pub(super) trait HostFloat: Backend {
    /// Runs `f` on the row-major f32 values of `t`; `None` when `t` is not f32.
    fn with_f32<R>(t: &FloatTensor<Self>, f: impl FnOnce(&[f32]) -> R) -> Option<R>;

    /// A tensor of `shape` holding `values` (row-major), on the device of `like`.
    fn from_f32(values: Vec<f32>, shape: Shape, like: &FloatTensor<Self>) -> FloatTensor<Self>;
}

#[cfg(feature = "flex")]
impl HostFloat for burn::backend::Flex {
    fn with_f32<R>(t: &FloatTensor<Self>, f: impl FnOnce(&[f32]) -> R) -> Option<R> {
        if t.dtype() != DType::F32 {
            return None;
        }
        match t.as_slice::<f32>() {
            Some(values) => Some(f(values)),
            None => t.to_contiguous().as_slice::<f32>().map(f),
        }
    }

    fn from_f32(values: Vec<f32>, shape: Shape, _like: &FloatTensor<Self>) -> FloatTensor<Self> {
        burn::backend::flex::FlexTensor::from_data(TensorData::new(values, shape))
    }
}

#[cfg(feature = "ndarray")]
#[allow(deprecated)]
impl HostFloat for burn::backend::NdArray {
    fn with_f32<R>(t: &FloatTensor<Self>, f: impl FnOnce(&[f32]) -> R) -> Option<R> {
        use burn::backend::ops::FloatTensorOps;
        if t.dtype() != DType::F32 {
            return None;
        }
        let data = burn::tensor::try_read_sync(Self::float_into_data(t.clone()))?.ok()?;
        data.as_slice::<f32>().ok().map(f)
    }

    fn from_f32(values: Vec<f32>, shape: Shape, like: &FloatTensor<Self>) -> FloatTensor<Self> {
        use burn::backend::ops::FloatTensorOps;
        Self::float_from_data(TensorData::new(values, shape), &like.device())
    }
}

/// `f` applied to the values of `x` (an output of `x`'s shape); `Err(x)` when `x` is not f32
/// or `f` returns a wrong length, for the caller's composed fallback.
pub(super) fn map<B: HostFloat>(
    x: FloatTensor<B>,
    f: impl FnOnce(&[f32]) -> Vec<f32>,
) -> Result<FloatTensor<B>, FloatTensor<B>> {
    let shape = x.shape();
    match B::with_f32(&x, f) {
        Some(values) if values.len() == shape.num_elements() => Ok(B::from_f32(values, shape, &x)),
        _ => Err(x),
    }
}

/// `f` applied to the values of `a` and `b` (one shape; the output has it too); `Err((a, b))`
/// when either is not f32, the shapes differ or `f` returns a wrong length.
pub(super) fn zip<B: HostFloat>(
    a: FloatTensor<B>,
    b: FloatTensor<B>,
    f: impl FnOnce(&[f32], &[f32]) -> Vec<f32>,
) -> Result<FloatTensor<B>, (FloatTensor<B>, FloatTensor<B>)> {
    let shape = a.shape();
    if b.shape() != shape {
        return Err((a, b));
    }
    let values = B::with_f32(&a, |av| B::with_f32(&b, |bv| f(av, bv))).flatten();
    match values {
        Some(values) if values.len() == shape.num_elements() => Ok(B::from_f32(values, shape, &a)),
        _ => Err((a, b)),
    }
}
