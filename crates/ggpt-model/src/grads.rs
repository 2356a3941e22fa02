//! Gradient arithmetic over Burn's [`GradientsParams`], for any [`Module`].
//!
//! [`GradientsParams`] holds one tensor per parameter id, of the parameter's rank, so sums,
//! scalings and norms need a walk over the module's parameters ([`ModuleVisitor`]) to learn each
//! id's rank. These functions are those walks, shared by the training step (clipping, adding the
//! gradients of micro-batches and replicas) and segment recomputation ([`crate::recompute`]:
//! collecting each segment's parameter gradients). Every walk visits the parameters in the
//! module's order, so results are reproducible.

use burn::module::{Module, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::{Gradients, Tensor};

use crate::Result;
use crate::readback::read_tensor_f32;

/// `a + b` for every parameter of `model` (a missing side counts as 0); `b`'s gradient is moved
/// to the device of `a`'s.
pub fn add<M: Module>(model: &M, a: GradientsParams, b: GradientsParams) -> GradientsParams {
    struct Add {
        a: GradientsParams,
        b: GradientsParams,
    }
    impl ModuleVisitor for Add {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let sum = match (self.a.remove::<D>(param.id), self.b.remove::<D>(param.id)) {
                (Some(x), Some(y)) => {
                    let device = x.device();
                    Some(x + y.to_device(&device))
                }
                (x, y) => x.or(y),
            };
            if let Some(g) = sum {
                self.a.register::<D>(param.id, g);
            }
        }
    }
    let mut add = Add { a, b };
    model.visit(&mut add);
    add.a
}

/// Multiplies the gradient of every parameter of `model` present in `grads` by `factor`.
pub fn scale<M: Module>(model: &M, grads: &mut GradientsParams, factor: f64) {
    struct Scale<'a> {
        grads: &'a mut GradientsParams,
        factor: f64,
    }
    impl ModuleVisitor for Scale<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.grads.remove::<D>(param.id) {
                self.grads
                    .register::<D>(param.id, g.mul_scalar(self.factor));
            }
        }
    }
    model.visit(&mut Scale { grads, factor });
}

/// The sum of squares of the gradient of every parameter of `model` present in `grads`, one
/// `[1]` tensor per parameter, in visiting order.
pub fn squared_norm_parts<M: Module>(model: &M, grads: &GradientsParams) -> Vec<Tensor<1>> {
    struct Sq<'a> {
        grads: &'a GradientsParams,
        parts: Vec<Tensor<1>>,
    }
    impl ModuleVisitor for Sq<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.grads.get::<D>(param.id) {
                self.parts.push(g.square().sum());
            }
        }
    }
    let mut sq = Sq {
        grads,
        parts: Vec::new(),
    };
    model.visit(&mut sq);
    sq.parts
}

/// Global L2 norm of the gradients of `model`'s parameters: the [`squared_norm_parts`]
/// concatenated and summed on the device, read back as `f32`, and its square root in `f64`.
/// 0 without any gradient.
pub fn global_norm<M: Module>(model: &M, grads: &GradientsParams) -> Result<f64> {
    let parts = squared_norm_parts(model, grads);
    if parts.is_empty() {
        return Ok(0.0);
    }
    let total = Tensor::cat(parts, 0).sum();
    Ok((read_tensor_f32(&total, "grad norm")?
        .first()
        .copied()
        .unwrap_or(0.0) as f64)
        .sqrt())
}

/// Adds `g` to the gradient `acc` holds for parameter `id` (`g` alone if it holds none).
pub fn accumulate<const D: usize>(acc: &mut GradientsParams, id: ParamId, g: Tensor<D>) {
    let g = match acc.remove::<D>(id) {
        Some(prev) => prev + g,
        None => g,
    };
    acc.register::<D>(id, g);
}

/// Moves the gradient of every parameter of `model` present in the autodiff `grads` into `acc`,
/// adding it to what `acc` already holds for that parameter ([`accumulate`]).
pub fn collect<M: Module>(model: &M, grads: &mut Gradients, acc: &mut GradientsParams) {
    struct Collect<'a> {
        grads: &'a mut Gradients,
        acc: &'a mut GradientsParams,
    }
    impl ModuleVisitor for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = param.val().grad_remove(self.grads) {
                accumulate(self.acc, param.id, g);
            }
        }
    }
    model.visit(&mut Collect { grads, acc });
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::tensor::Device;

    fn device() -> Device {
        Device::flex().autodiff()
    }

    /// A 3 -> 2 linear layer (weight `[3, 2]`, bias `[2]`).
    fn linear() -> Linear {
        LinearConfig::new(3, 2).init(&device())
    }

    /// The gradients of `sum(linear(x))` for the input `x` (`[n, 3]`, row-major).
    fn grads_of(model: &Linear, x: &[f32], n: usize) -> GradientsParams {
        let x = Tensor::<1>::from_floats(x, &device()).reshape([n, 3]);
        let loss = model.forward(x).sum();
        GradientsParams::from_grads(loss.backward(), model)
    }

    fn values<const D: usize>(g: &GradientsParams, param: &Param<Tensor<D>>) -> Vec<f32> {
        g.get::<D>(param.id)
            .unwrap()
            .into_data()
            .convert::<f32>()
            .try_to_vec::<f32>()
            .unwrap()
    }

    /// Weight and bias gradients of one `GradientsParams`, flattened.
    fn all(model: &Linear, g: &GradientsParams) -> Vec<f32> {
        let mut v = values(g, &model.weight);
        v.extend(values(g, model.bias.as_ref().unwrap()));
        v
    }

    #[test]
    fn added_gradients_are_the_elementwise_sum() {
        let model = linear();
        let a = grads_of(&model, &[1.0, 2.0, 3.0], 1);
        let b = grads_of(&model, &[-0.5, 4.0, 0.25, 1.0, 1.0, 1.0], 2);
        let (va, vb) = (all(&model, &a), all(&model, &b));
        let sum = add(&model, a, b);
        let want: Vec<f32> = va.iter().zip(&vb).map(|(x, y)| x + y).collect();
        assert_eq!(all(&model, &sum), want);
        // a missing side counts as 0
        let only = add(
            &model,
            GradientsParams::new(),
            grads_of(&model, &[1.0, 2.0, 3.0], 1),
        );
        assert_eq!(all(&model, &only), va);
    }

    #[test]
    fn scaling_by_one_half_halves_every_gradient() {
        let model = linear();
        let mut g = grads_of(&model, &[1.0, -2.0, 3.0, 0.5, 0.5, 0.5], 2);
        let before = all(&model, &g);
        scale(&model, &mut g, 0.5);
        let want: Vec<f32> = before.iter().map(|x| x * 0.5).collect();
        assert_eq!(all(&model, &g), want);
    }

    #[test]
    fn global_norm_is_the_l2_norm_of_all_gradients() {
        let model = linear();
        let g = grads_of(&model, &[1.0, 2.0, 3.0, -1.0, 0.0, 2.0], 2);
        // d sum(x W + b) / dW[i][j] = sum over rows of x[., i]; / db[j] = rows
        let (col, rows) = ([0.0f64, 2.0, 5.0], 2.0f64);
        let want = (2.0 * col.iter().map(|c| c * c).sum::<f64>() + 2.0 * rows * rows).sqrt();
        assert_eq!(
            all(&model, &g),
            vec![0.0, 0.0, 2.0, 2.0, 5.0, 5.0, 2.0, 2.0]
        );
        let norm = global_norm(&model, &g).unwrap();
        assert!((norm - want).abs() < 1e-6, "{norm} vs {want}");
        assert_eq!(squared_norm_parts(&model, &g).len(), 2);
        assert_eq!(global_norm(&model, &GradientsParams::new()).unwrap(), 0.0);
    }

    #[test]
    fn collected_gradients_accumulate() {
        let model = linear();
        let x = || Tensor::<1>::from_floats([1.0, 2.0, 3.0], &device()).reshape([1, 3]);
        let mut acc = GradientsParams::new();
        for _ in 0..2 {
            let mut grads = model.forward(x()).sum().backward();
            collect(&model, &mut grads, &mut acc);
        }
        let once = all(&model, &grads_of(&model, &[1.0, 2.0, 3.0], 1));
        let want: Vec<f32> = once.iter().map(|v| v * 2.0).collect();
        assert_eq!(all(&model, &acc), want);
        // accumulate adds to what is held
        let bias = model.bias.as_ref().unwrap();
        accumulate(
            &mut acc,
            bias.id,
            Tensor::<1>::from_floats([1.0, -1.0], &device()),
        );
        assert_eq!(values(&acc, bias), vec![want[6] + 1.0, want[7] - 1.0]);
    }
}
