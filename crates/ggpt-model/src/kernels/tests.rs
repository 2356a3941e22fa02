//! Each op of the kernel layer against its definition: the host kernels against the composed
//! default body, and the op's `Backward` against autodiff of the composed body, on both CPU
//! backends; GELU against an f64 reference.

use burn::backend::Dispatch;
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::{
    GgptKernels, SCORE_BUDGET_FLOATS, attention, composed, conv, gather_rows, gelu, layer_norm,
    subm_conv, window_attention,
};
use crate::host_attention::WindowShape;
use crate::prepared::{ConvIndex, NUM_TAPS};

/// erf in f64 (Abramowitz-Stegun 7.1.26 is too coarse; use a series / continued fraction).
fn erf64(x: f64) -> f64 {
    // Taylor series converges well for |x| < 3; beyond, 1 - erfc asymptotics are ~1.
    if x.abs() > 5.0 {
        return x.signum();
    }
    let mut sum: f64 = 0.0;
    let mut term = x;
    let mut n = 0.0;
    while term.abs() > 1e-17 * sum.abs().max(1e-300) || n < 5.0 {
        sum += term / (2.0 * n + 1.0);
        n += 1.0;
        term *= -x * x / n;
        if n > 200.0 {
            break;
        }
    }
    sum * 2.0 / std::f64::consts::PI.sqrt()
}

/// The CPU devices under test, with autodiff (pushed one by one: each is behind its feature).
#[allow(clippy::vec_init_then_push)]
fn devices() -> Vec<Device> {
    let mut out = Vec::new();
    #[cfg(feature = "flex")]
    out.push(Device::flex().autodiff());
    #[cfg(feature = "ndarray")]
    out.push(Device::ndarray().autodiff());
    out
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().to_vec().expect("f32")
}

/// Deterministic values in `[-4, 4)`: a fixed LCG.
fn spread(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 8.0 - 4.0
        })
        .collect()
}

fn assert_close(got: &[f32], want: &[f32], tol: f32, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= tol * (1.0 + w.abs()),
            "{what}[{i}]: {g} vs {w}"
        );
    }
}

/// The composed GELU as a tensor expression (autodiff differentiates it op by op).
fn composed_gelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    Tensor::from_dispatch(composed::gelu::<Dispatch>(x.into_dispatch()))
}

#[test]
fn gelu_forward_and_gradient_are_exact() {
    for device in devices() {
        let xs: Vec<f32> = (-40..=40).map(|i| i as f32 * 0.1).collect();
        let n = xs.len();
        let x = Tensor::<1>::from_data(TensorData::new(xs.clone(), [n]), &device).require_grad();
        let y = gelu(x.clone());
        let grads = y.clone().sum().backward();
        let gx = values(x.grad(&grads).expect("grad"));
        let yv = values(y);
        for (i, &xi) in xs.iter().enumerate() {
            let x64 = xi as f64;
            let want = 0.5 * x64 * (1.0 + erf64(x64 / 2f64.sqrt()));
            let dwant = 0.5 * (1.0 + erf64(x64 / 2f64.sqrt()))
                + x64 * (-x64 * x64 / 2.0).exp() / (2.0 * std::f64::consts::PI).sqrt();
            assert!(
                (yv[i] as f64 - want).abs() < 2e-6,
                "{device:?} gelu({xi}) = {} want {want}",
                yv[i]
            );
            assert!(
                (gx[i] as f64 - dwant).abs() < 2e-6,
                "{device:?} gelu'({xi}) = {} want {dwant}",
                gx[i]
            );
        }
    }
}

#[test]
fn gelu_backward_equals_autodiff_of_the_composed_body() {
    for device in devices() {
        let (n, c) = (37, 11);
        let xs = spread(n * c, 1);
        let ws = spread(n * c, 2);
        let w = Tensor::<2>::from_data(TensorData::new(ws, [n, c]), &device);
        let run = |f: &dyn Fn(Tensor<2>) -> Tensor<2>| {
            let x =
                Tensor::<2>::from_data(TensorData::new(xs.clone(), [n, c]), &device).require_grad();
            let y = f(x.clone());
            let grads = (y.clone() * w.clone()).sum().backward();
            (values(y), values(x.grad(&grads).expect("grad")))
        };
        let (y_op, g_op) = run(&|x| gelu(x));
        let (y_ref, g_ref) = run(&|x| composed_gelu(x));
        assert_close(&y_op, &y_ref, 1e-6, "gelu forward");
        assert_close(&g_op, &g_ref, 1e-6, "gelu backward");
    }
}

#[test]
fn gelu_without_a_graph_equals_the_composed_body() {
    for device in devices() {
        let device = device.inner();
        let xs = spread(4099, 3);
        let x = Tensor::<1>::from_data(TensorData::new(xs.clone(), [xs.len()]), &device);
        assert_close(
            &values(gelu(x.clone())),
            &values(composed_gelu(x)),
            1e-6,
            "gelu",
        );
        // A strided (non-contiguous) input goes through the same kernel.
        let m = Tensor::<1>::from_data(TensorData::new(xs[..4096].to_vec(), [4096]), &device)
            .reshape([64, 64])
            .transpose();
        assert_close(
            &values(gelu(m.clone())),
            &values(composed_gelu(m)),
            1e-6,
            "strided gelu",
        );
    }
}

#[test]
fn gather_rows_backward_sums_repeated_rows() {
    for device in devices() {
        let (n, c) = (5, 3);
        let xs = spread(n * c, 4);
        let idx = [0i64, 2, 2, 4, 0, 1, 0];
        let m = idx.len();
        let ws = spread(m * c, 5);
        let w = Tensor::<2>::from_data(TensorData::new(ws.clone(), [m, c]), &device);
        let run = |f: &dyn Fn(Tensor<2>, Tensor<1, Int>) -> Tensor<2>| {
            let x =
                Tensor::<2>::from_data(TensorData::new(xs.clone(), [n, c]), &device).require_grad();
            let i = Tensor::<1, Int>::from_data(TensorData::new(idx.to_vec(), [m]), &device);
            let y = f(x.clone(), i);
            let grads = (y.clone() * w.clone()).sum().backward();
            (values(y), values(x.grad(&grads).expect("grad")))
        };
        let (y_op, g_op) = run(&|x, i| gather_rows(x, i));
        let (y_ref, g_ref) = run(&|x, i| x.select(0, i));
        assert_eq!(y_op, y_ref, "gather forward");
        assert_close(&g_op, &g_ref, 1e-6, "gather backward");
        // By hand: row r receives the sum of the weights of the picks of r.
        let mut want = vec![0.0f32; n * c];
        for (k, &r) in idx.iter().enumerate() {
            for j in 0..c {
                want[r as usize * c + j] += ws[k * c + j];
            }
        }
        assert_close(&g_op, &want, 1e-6, "gather backward by hand");
    }
}

#[test]
fn the_atomic_row_scatter_equals_the_default() {
    for device in devices() {
        let device = device.inner();
        let (m, c, rows) = (9, 4, 6);
        let g = Tensor::<2>::from_data(TensorData::new(spread(m * c, 6), [m, c]), &device);
        let idx = Tensor::<1, Int>::from_data(
            TensorData::new(vec![5i64, 0, 0, 3, 5, 1, 2, 0, 4], [m]),
            &device,
        );
        let default = Tensor::<2>::from_dispatch(<Dispatch as GgptKernels>::scatter_add_rows(
            g.clone().into_dispatch(),
            idx.clone().into_dispatch(),
            rows,
        ));
        let atomic = Tensor::<2>::from_dispatch(super::rows::scatter_add_rows_atomic::<Dispatch>(
            g.into_dispatch(),
            idx.into_dispatch(),
            rows,
        ));
        assert_close(&values(atomic), &values(default), 1e-6, "row scatter");
    }
}

#[test]
fn layer_norm_backward_equals_autodiff_of_the_composed_body() {
    for device in devices() {
        let (n, c) = (29, 13);
        let eps = 1e-5;
        let xs: Vec<f32> = spread(n * c, 7).iter().map(|v| v * 3.0 + 1.0).collect();
        let gs = spread(c, 8);
        let bs = spread(c, 9);
        let w = Tensor::<2>::from_data(TensorData::new(spread(n * c, 10), [n, c]), &device);
        let run = |f: &dyn Fn(Tensor<2>, Tensor<1>, Tensor<1>) -> Tensor<2>| {
            let x =
                Tensor::<2>::from_data(TensorData::new(xs.clone(), [n, c]), &device).require_grad();
            let g =
                Tensor::<1>::from_data(TensorData::new(gs.clone(), [c]), &device).require_grad();
            let b =
                Tensor::<1>::from_data(TensorData::new(bs.clone(), [c]), &device).require_grad();
            let y = f(x.clone(), g.clone(), b.clone());
            let grads = (y.clone() * w.clone()).sum().backward();
            (
                values(y),
                values(x.grad(&grads).expect("dx")),
                values(g.grad(&grads).expect("dgamma")),
                values(b.grad(&grads).expect("dbeta")),
            )
        };
        let op = run(&|x, g, b| layer_norm(x, g, Some(b), eps));
        // Burn's LayerNorm under autodiff: differentiated op by op.
        let reference = run(&|x, g, b| burn::tensor::module::layer_norm(x, g, Some(b), eps));
        assert_close(&op.0, &reference.0, 1e-5, "layer norm forward");
        assert_close(&op.1, &reference.1, 1e-5, "layer norm dx");
        assert_close(&op.2, &reference.2, 1e-5, "layer norm dgamma");
        assert_close(&op.3, &reference.3, 1e-5, "layer norm dbeta");
        // The composed backward body (what CubeCL runs) agrees with the host backward.
        let inner = device.clone().inner();
        let x = Tensor::<2>::from_data(TensorData::new(xs.clone(), [n, c]), &inner);
        let g = Tensor::<1>::from_data(TensorData::new(gs.clone(), [c]), &inner);
        let dy = w.clone().inner();
        let (dx, dg, db) = composed::layer_norm_backward::<Dispatch>(
            x.into_dispatch(),
            g.into_dispatch(),
            dy.into_dispatch(),
            eps,
        );
        assert_close(
            &values(Tensor::<2>::from_dispatch(dx)),
            &op.1,
            1e-5,
            "composed dx",
        );
        assert_close(
            &values(Tensor::<1>::from_dispatch(dg)),
            &op.2,
            1e-5,
            "composed dgamma",
        );
        assert_close(
            &values(Tensor::<1>::from_dispatch(db)),
            &op.3,
            1e-5,
            "composed dbeta",
        );
    }
}

#[test]
fn untracked_inputs_on_an_autodiff_device_stay_on_it() {
    for device in devices() {
        let (n, c) = (6, 5);
        let x = Tensor::<2>::from_data(TensorData::new(spread(n * c, 11), [n, c]), &device);
        let g = Tensor::<1>::ones([c], &device);
        let y = layer_norm(gelu(x), g, None, 1e-5);
        assert_eq!(
            y.device(),
            device,
            "an untracked op result keeps the autodiff device"
        );
        // ... and combines with a tracked tensor into a graph that reaches the tracked leaf.
        let t = Tensor::<2>::ones([n, c], &device).require_grad();
        let grads = (y * t.clone()).sum().backward();
        assert!(t.grad(&grads).is_some());
    }
}

/// A window shape with several windows and heads, its rows `[W L, 3C]` and an output weight
/// `[W L, C]` (the surrogate loss `Σ w ⊙ out`).
fn attention_case(seed: u64) -> (WindowShape, Vec<f32>, Vec<f32>) {
    let shape = WindowShape {
        windows: 3,
        len: 20,
        heads: 2,
        head_dim: 8,
    };
    let m = shape.windows * shape.len;
    // rows in [-1, 1): scores of a realistic spread
    let rows = spread(m * 3 * shape.channels(), seed)
        .into_iter()
        .map(|v| v / 4.0)
        .collect();
    (shape, rows, spread(m * shape.channels(), seed + 1))
}

/// `(out, d rows)` of `f(rows)` under autodiff with the surrogate loss `Σ w ⊙ out`.
fn attention_grads(
    device: &Device,
    shape: WindowShape,
    rows: &[f32],
    w: &[f32],
    f: &dyn Fn(Tensor<2>) -> Tensor<2>,
) -> (Vec<f32>, Vec<f32>) {
    let m = shape.windows * shape.len;
    let c = shape.channels();
    let x =
        Tensor::<2>::from_data(TensorData::new(rows.to_vec(), [m, 3 * c]), device).require_grad();
    let wt = Tensor::<2>::from_data(TensorData::new(w.to_vec(), [m, c]), device);
    let y = f(x.clone());
    let grads = (y.clone() * wt).sum().backward();
    (values(y), values(x.grad(&grads).expect("grad")))
}

/// The composed attention as a tensor expression with a score budget.
fn composed_attention(rows: Tensor<2>, shape: WindowShape, budget: usize) -> Tensor<2> {
    Tensor::from_dispatch(attention::window_attention::<Dispatch>(
        rows.into_dispatch(),
        shape,
        budget,
    ))
}

/// The op (host kernels forward and backward under its `Backward`) equals autodiff of the
/// composed body, whole and one window per sub-group.
#[test]
fn window_attention_backward_equals_autodiff_of_the_composed_body() {
    for device in devices() {
        let (shape, rows, w) = attention_case(7);
        let (y_op, g_op) =
            attention_grads(&device, shape, &rows, &w, &|x| window_attention(x, shape));
        let per_window = shape.heads * shape.len * shape.len;
        for budget in [SCORE_BUDGET_FLOATS, per_window] {
            let (y_ref, g_ref) = attention_grads(&device, shape, &rows, &w, &|x| {
                composed_attention(x, shape, budget)
            });
            assert_close(&y_op, &y_ref, 1e-5, "attention forward");
            assert_close(&g_op, &g_ref, 1e-5, "attention backward");
        }
    }
}

/// The composed backward (what CubeCL runs), whole and one window per sub-group, equals
/// autodiff of the composed forward.
#[test]
fn composed_attention_backward_equals_autodiff_of_the_composed_forward() {
    for device in devices() {
        let (shape, rows, w) = attention_case(9);
        let (_, want) = attention_grads(&device, shape, &rows, &w, &|x| {
            composed_attention(x, shape, SCORE_BUDGET_FLOATS)
        });
        let inner = device.inner();
        let m = shape.windows * shape.len;
        let c = shape.channels();
        let per_window = shape.heads * shape.len * shape.len;
        for budget in [SCORE_BUDGET_FLOATS, per_window, 2 * per_window] {
            let x = Tensor::<2>::from_data(TensorData::new(rows.clone(), [m, 3 * c]), &inner);
            let g = Tensor::<2>::from_data(TensorData::new(w.clone(), [m, c]), &inner);
            let got = Tensor::<2>::from_dispatch(attention::window_attention_backward::<Dispatch>(
                x.into_dispatch(),
                g.into_dispatch(),
                shape,
                budget,
            ));
            assert_close(&values(got), &want, 1e-5, "composed attention backward");
        }
    }
}

/// Burn's fused attention, called as CubeCL inference calls it (`scale = None`), equals the
/// composed `softmax((q s) kᵀ) v`: same layout, same scale.
fn fused_attention_equals_composed_on(device: &Device) {
    let (shape, rows, _) = attention_case(11);
    let m = shape.windows * shape.len;
    let x = Tensor::<2>::from_data(TensorData::new(rows, [m, 3 * shape.channels()]), device);
    let fused = Tensor::<2>::from_dispatch(attention::window_attention_fused::<Dispatch>(
        x.clone().into_dispatch(),
        shape,
    ));
    let composed = composed_attention(x, shape, SCORE_BUDGET_FLOATS);
    assert_close(&values(fused), &values(composed), 1e-5, "fused attention");
}

#[test]
fn fused_attention_equals_the_composed_body() {
    for device in devices() {
        fused_attention_equals_composed_on(&device.inner());
    }
}

/// The same on wgpu (Burn's fallback without the `autotune` feature, the flash kernel where
/// autotune picks it).
#[cfg(feature = "wgpu")]
#[test]
fn fused_attention_equals_the_composed_body_on_wgpu() {
    fused_attention_equals_composed_on(&crate::device::device_from_name("wgpu").expect("wgpu"));
}

/// A hand-made neighbour table: `n` tokens, two summed groups, every slot pointing at a token,
/// a group row or the zero row `N + G` ("no neighbour") by a fixed rule; tap 13 the identity.
fn conv_case(device: &Device, n: usize) -> ConvIndex {
    let groups = 2;
    let members = [1usize, 4, 5, 7];
    let ids = [0usize, 0, 1, 1];
    let empty = n + groups;
    let mut im2col = vec![0usize; n * NUM_TAPS];
    for t in 0..n {
        for f in 0..NUM_TAPS {
            let h = (t * 31 + f * 17) % 11;
            im2col[t * NUM_TAPS + f] = match (f, h) {
                (13, _) => t,
                (_, 0..=3) => empty,
                (_, 4) => n + (t + f) % groups,
                _ => (t + f * 5) % n,
            };
        }
    }
    let (packed, layout) = crate::conv_layout::pack(n, &im2col, &members, &ids, groups);
    let packed: Vec<i64> = packed.into_iter().map(|v| v as i64).collect();
    let len = packed.len();
    ConvIndex {
        tables: Tensor::<1, Int>::from_data(TensorData::new(packed, [len]), device),
        layout,
    }
}

/// `(out, d x, d weight, d bias)` of `f(x, weight, bias)` under autodiff with the surrogate
/// loss `Σ w ⊙ out`.
type ConvRun = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>);

fn conv_grads(
    device: &Device,
    n: usize,
    (c_in, c_out): (usize, usize),
    f: &dyn Fn(Tensor<2>, Tensor<5>, Tensor<1>) -> Tensor<2>,
) -> ConvRun {
    let x = Tensor::<2>::from_data(TensorData::new(spread(n * c_in, 21), [n, c_in]), device)
        .require_grad();
    let w = Tensor::<5>::from_data(
        TensorData::new(spread(c_out * NUM_TAPS * c_in, 22), [c_out, 3, 3, 3, c_in]),
        device,
    )
    .require_grad();
    let b =
        Tensor::<1>::from_data(TensorData::new(spread(c_out, 23), [c_out]), device).require_grad();
    let weight = Tensor::<2>::from_data(TensorData::new(spread(n * c_out, 24), [n, c_out]), device);
    let y = f(x.clone(), w.clone(), b.clone());
    let grads = (y.clone() * weight).sum().backward();
    (
        values(y),
        values(x.grad(&grads).expect("d x")),
        values(w.grad(&grads).expect("d weight")),
        values(b.grad(&grads).expect("d bias")),
    )
}

/// The composed im2col conv as a tensor expression.
fn composed_conv(x: Tensor<2>, w: Tensor<5>, b: Tensor<1>, index: &ConvIndex) -> Tensor<2> {
    Tensor::from_dispatch(conv::subm_conv_im2col::<Dispatch>(
        x.into_dispatch(),
        w.into_dispatch(),
        b.into_dispatch(),
        &index.tables.clone().into_dispatch(),
        &index.layout,
    ))
}

fn assert_conv_close(got: &ConvRun, want: &ConvRun, what: &str) {
    assert_close(&got.0, &want.0, 1e-5, &format!("{what}: out"));
    assert_close(&got.1, &want.1, 1e-5, &format!("{what}: d x"));
    assert_close(&got.2, &want.2, 1e-5, &format!("{what}: d weight"));
    assert_close(&got.3, &want.3, 1e-5, &format!("{what}: d bias"));
}

/// The conv op (the tap-wise forward and the host backward on the CPU backends) equals autodiff
/// of the composed im2col body: output, and gradients of the input, weight and bias, with
/// summed groups and empty slots.
#[test]
fn subm_conv_backward_equals_autodiff_of_the_composed_body() {
    for device in devices() {
        let (n, channels) = (40, (5, 6));
        let index = conv_case(&device, n);
        assert!(
            conv::tapwise(&index.layout),
            "the CPU backends take the tap-wise form"
        );
        assert!(index.layout.groups().is_some() && index.layout.taps.len() == NUM_TAPS);
        let op = conv_grads(&device, n, channels, &|x, w, b| subm_conv(x, w, b, &index));
        let want = conv_grads(&device, n, channels, &|x, w, b| {
            composed_conv(x, w, b, &index)
        });
        assert_conv_close(&op, &want, "subm conv");
    }
}

/// The composed backward (what CubeCL runs) equals autodiff of the composed forward.
#[test]
fn composed_conv_backward_equals_autodiff_of_the_composed_forward() {
    for device in devices() {
        let (n, (c_in, c_out)) = (40, (5, 6));
        let index = conv_case(&device, n);
        let want = conv_grads(&device, n, (c_in, c_out), &|x, w, b| {
            composed_conv(x, w, b, &index)
        });
        let inner = device.inner();
        let index = conv_case(&inner, n);
        let x = Tensor::<2>::from_data(TensorData::new(spread(n * c_in, 21), [n, c_in]), &inner);
        let w = Tensor::<5>::from_data(
            TensorData::new(spread(c_out * NUM_TAPS * c_in, 22), [c_out, 3, 3, 3, c_in]),
            &inner,
        );
        let g = Tensor::<2>::from_data(TensorData::new(spread(n * c_out, 24), [n, c_out]), &inner);
        let (dx, dw, db) = conv::subm_conv_backward_composed::<Dispatch>(
            x.into_dispatch(),
            w.into_dispatch(),
            g.into_dispatch(),
            &index.tables.clone().into_dispatch(),
            &index.layout,
        );
        let got = (
            want.0.clone(),
            values(Tensor::<2>::from_dispatch(dx)),
            values(Tensor::<5>::from_dispatch(dw)),
            values(Tensor::<1>::from_dispatch(db)),
        );
        assert_conv_close(&got, &want, "composed conv backward");
    }
}

/// The host-kernel query is routed by the backend type: true on the CPU backends, with and
/// without autodiff.
#[test]
fn the_cpu_backends_run_on_the_host() {
    for device in devices() {
        for d in [device.clone(), device.inner()] {
            let probe = Tensor::<2>::zeros([1, 1], &d);
            assert!(super::runs_on_host(&probe), "{d:?}");
        }
    }
}

/// ... and false on CubeCL.
#[cfg(feature = "wgpu")]
#[test]
fn wgpu_does_not_run_on_the_host() {
    let device = crate::device::device_from_name("wgpu").expect("wgpu");
    for d in [device.clone(), device.autodiff()] {
        assert!(
            !super::runs_on_host(&Tensor::<2>::zeros([1, 1], &d)),
            "{d:?}"
        );
    }
}
