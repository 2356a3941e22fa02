//! Submanifold sparse convolution, kernel 3 (network.md §6), spconv CPU duplicate rule.
//!
//! Weight kept in the checkpoint's spconv "KRSC" layout `[C_out, 3, 3, 3, C_in]` (no adapter
//! touches it); tap `f = 9 r0 + 3 r1 + r2` has matrix `W_f = weight[:, r0, r1, r2, :]`. The
//! convolution is the kernel layer's op [`crate::kernels::subm_conv`] (the im2col GEMM, or on
//! the CPU backends the tap-wise form for sparse neighbourhoods; [`crate::kernels::conv`]),
//! whose `Backward` differentiates it.

use burn::module::{Module, Param};
use burn::nn::Initializer;
use burn::tensor::{Device, Tensor};

use crate::prepared::{ConvIndex, NUM_TAPS};

/// spconv `SubMConv3d(C_in, C_out, kernel 3, bias)`.
#[derive(Module, Debug)]
pub struct SubmConv3d {
    /// `[C_out, 3, 3, 3, C_in]` (KRSC).
    pub weight: Param<Tensor<5>>,
    /// `[C_out]`.
    pub bias: Param<Tensor<1>>,
}

impl SubmConv3d {
    /// Initialised `U(±1/sqrt(27 C_in))` (network.md §11.4).
    pub fn new(c_in: usize, c_out: usize, device: &Device) -> Self {
        let bound = 1.0 / ((NUM_TAPS * c_in) as f64).sqrt();
        let init = Initializer::Uniform {
            min: -bound,
            max: bound,
        };
        Self {
            weight: init.init([c_out, 3, 3, 3, c_in], device),
            bias: init.init([c_out], device),
        }
    }

    /// `x [N, C_in] -> [N, C_out]` over the level's neighbour tables.
    ///
    /// The CPU backends with sparse neighbourhoods ([`crate::conv_layout::ConvLayout::occupancy`] below
    /// [`crate::kernels::conv::TAPWISE_MAX_OCCUPANCY`]) use the tap-wise form (only occupied
    /// slots are multiplied); other backends the im2col GEMM. Both compute the same sums (up to
    /// f32 rounding order).
    pub fn forward(&self, x: Tensor<2>, index: &ConvIndex) -> Tensor<2> {
        let [n, _] = x.dims();
        let [c_out, _, _, _, _] = self.weight.dims();
        if n == 0 {
            return Tensor::zeros([0, c_out], &x.device());
        }
        crate::kernels::subm_conv(x, self.weight.val(), self.bias.val(), index)
    }
}
