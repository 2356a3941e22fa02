//! Residual head (network.md §10).
//!
//! ```text
//! head_in = [backbone.out | input.feat]                 [N, D_0 + 218]
//! h       = fc3(ReLU(fc2(ReLU(fc1(head_in)))))          [N, 4]     fixture head.pre_activation
//! xyz     = coord + h[:, 0..3]                          [N, 3]     normalised chunk coordinates
//! conf    = 1 + exp(h[:, 3])                            [N]        >= 1
//! ```

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

/// Official `head.0`, `head.2`, `head.4`.
#[derive(Module, Debug)]
pub struct Head {
    /// `Linear(D_0 + 218 -> W)`.
    pub fc1: Linear,
    /// `Linear(W -> W)`.
    pub fc2: Linear,
    /// `Linear(W -> 4)`.
    pub fc3: Linear,
}

impl Head {
    /// New head; the last layer is zero-initialised (identity start, confidence 2, §11.4).
    pub fn new(c_in: usize, width: usize, device: &Device) -> Self {
        Self {
            fc1: LinearConfig::new(c_in, width).init(device),
            fc2: LinearConfig::new(width, width).init(device),
            fc3: LinearConfig::new(width, 4)
                .with_initializer(burn::nn::Initializer::Zeros)
                .init(device),
        }
    }

    /// `head_in [N, D_0 + 218] -> h [N, 4]` (pre-activation).
    pub fn forward(&self, head_in: Tensor<2>) -> Tensor<2> {
        self.fc3
            .forward(relu(self.fc2.forward(relu(self.fc1.forward(head_in)))))
    }
}

/// `(xyz [N, 3], conf [N])` from the pre-activation `h [N, 4]` and the token coordinates.
pub fn head_outputs(h: Tensor<2>, coord: Tensor<2>) -> (Tensor<2>, Tensor<1>) {
    let [n, _] = h.dims();
    let xyz = coord + h.clone().narrow(1, 0, 3);
    let conf = h.narrow(1, 3, 1).exp().add_scalar(1.0).reshape([n]);
    (xyz, conf)
}
