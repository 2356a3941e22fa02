//! [`GgptKernels`] under autodiff: one `Backward` per op, whose backward pass calls the inner
//! backend's backward op (host kernels on flex/ndarray, composed bodies on CubeCL). The
//! backward ops themselves (`gelu_backward`, `scatter_add_rows`) keep their default bodies here:
//! composed of autodiff primitives, they are differentiable again.

use burn::backend::Autodiff;
use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind, unary};
use burn::backend::tensor::{FloatTensor, IntTensor};

use super::GgptKernels;
use crate::conv_layout::ConvLayout;
use crate::host_attention::WindowShape;

/// The backward of `gelu`; state: the input `x`.
#[derive(Debug)]
struct GeluBackward;

impl<B: GgptKernels> Backward<B, 1> for GeluBackward {
    type State = FloatTensor<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let x = ops.state;
        unary::<B, _>(ops.parents, ops.node, grads, |grad| {
            B::gelu_exact_backward(x, grad)
        });
    }
}

/// The backward of `gather_rows`; state: the row index and the row count of the input.
#[derive(Debug)]
struct GatherRowsBackward;

impl<B: GgptKernels> Backward<B, 1> for GatherRowsBackward {
    type State = (IntTensor<B>, usize);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let (idx, rows) = ops.state;
        unary::<B, _>(ops.parents, ops.node, grads, |grad| {
            B::scatter_add_rows(grad, idx, rows)
        });
    }
}

/// The backward of `layer_norm_rows`; state: the input `x`, `gamma` and epsilon (the
/// statistics are recomputed: one pass, and no `[N, C]` kept beside `x`).
#[derive(Debug)]
struct LayerNormBackward;

impl<B: GgptKernels> Backward<B, 3> for LayerNormBackward {
    type State = (FloatTensor<B>, FloatTensor<B>, f64);

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let [x_node, gamma_node, beta_node] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x, gamma, eps) = ops.state;
        let (dx, d_gamma, d_beta) = B::layer_norm_rows_backward(x, gamma, grad, eps);
        for (node, g) in [(x_node, dx), (gamma_node, d_gamma), (beta_node, d_beta)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

/// The backward of `window_attention`; state: the projection rows and the window shape (the
/// probabilities are recomputed by the backward: no `[W, H, L, L]` tensor is kept).
#[derive(Debug)]
struct WindowAttentionBackward;

impl<B: GgptKernels> Backward<B, 1> for WindowAttentionBackward {
    type State = (FloatTensor<B>, WindowShape);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let (rows, shape) = ops.state;
        unary::<B, _>(ops.parents, ops.node, grads, |grad| {
            B::window_attention_backward(rows, grad, shape)
        });
    }
}

/// The backward of `subm_conv`; state: the input, the weight, the index tables and their
/// layout.
#[derive(Debug)]
struct SubmConvBackward;

impl<B: GgptKernels> Backward<B, 3> for SubmConvBackward {
    type State = (FloatTensor<B>, FloatTensor<B>, IntTensor<B>, ConvLayout);

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let [x_node, weight_node, bias_node] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight, tables, layout) = ops.state;
        let (dx, dw, db) = B::subm_conv_backward(x, weight, grad, tables, layout);
        for (node, g) in [(x_node, dx), (weight_node, dw), (bias_node, db)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

impl<B: GgptKernels, C: CheckpointStrategy> GgptKernels for Autodiff<B, C> {
    fn runs_on_host(probe: FloatTensor<Self>) -> bool {
        B::runs_on_host(probe.into_primitive())
    }

    fn subm_conv(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        tables: IntTensor<Self>,
        layout: ConvLayout,
    ) -> FloatTensor<Self> {
        match SubmConvBackward
            .prepare::<C>([x.node(), weight.node(), bias.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let (x, weight) = (x.into_primitive(), weight.into_primitive());
                let out = B::subm_conv(
                    x.clone(),
                    weight.clone(),
                    bias.into_primitive(),
                    tables.clone(),
                    layout.clone(),
                );
                prep.finish((x, weight, tables, layout), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::subm_conv(
                x.into_primitive(),
                weight.into_primitive(),
                bias.into_primitive(),
                tables,
                layout,
            )),
        }
    }

    fn window_attention(rows: FloatTensor<Self>, shape: WindowShape) -> FloatTensor<Self> {
        match WindowAttentionBackward
            .prepare::<C>([rows.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let rows = rows.into_primitive();
                prep.finish((rows.clone(), shape), B::window_attention(rows, shape))
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::window_attention(rows.into_primitive(), shape))
            }
        }
    }

    fn layer_norm_rows(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        eps: f64,
    ) -> FloatTensor<Self> {
        match LayerNormBackward
            .prepare::<C>([x.node(), gamma.node(), beta.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let (x, gamma) = (x.into_primitive(), gamma.into_primitive());
                let state = (x.clone(), gamma.clone(), eps);
                prep.finish(
                    state,
                    B::layer_norm_rows(x, gamma, beta.into_primitive(), eps),
                )
            }
            OpsKind::UnTracked(prep) => prep.finish(B::layer_norm_rows(
                x.into_primitive(),
                gamma.into_primitive(),
                beta.into_primitive(),
                eps,
            )),
        }
    }

    fn gelu_exact(x: FloatTensor<Self>) -> FloatTensor<Self> {
        match GeluBackward
            .prepare::<C>([x.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let input = x.into_primitive();
                prep.finish(input.clone(), B::gelu_exact(input))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::gelu_exact(x.into_primitive())),
        }
    }

    fn gather_rows(x: FloatTensor<Self>, idx: IntTensor<Self>) -> FloatTensor<Self> {
        let rows = x.shape()[0];
        match GatherRowsBackward
            .prepare::<C>([x.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                prep.finish((idx.clone(), rows), B::gather_rows(x.into_primitive(), idx))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::gather_rows(x.into_primitive(), idx)),
        }
    }
}
