//! A feed-forward network as flat buffers: its parameters in `burn`'s visiting order, the
//! per-thread activations of a chunk, and the chunked forward and backward passes.

use super::kernels::{gemm, tanh_backward, tanh_in_place};
use super::{AdamMoments, CHUNK};
use crate::batch::Batch;
use crate::model::values;
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Tensor, TensorData};

/// A feed-forward network as flat parameters (see the module doc for the layout).
#[derive(Clone, Debug)]
pub(super) struct FlatNet {
    /// Layer widths, input first.
    pub(super) sizes: Vec<usize>,
    /// Parameters.
    pub(super) params: Vec<f32>,
    /// Per layer: offsets of the weight and of the bias in `params`.
    pub(super) offsets: Vec<(usize, usize)>,
}

impl FlatNet {
    /// The parameters of `module` (an actor or a critic) whose MLP has layer widths `sizes`.
    pub(super) fn of<M: Module>(module: &M, sizes: Vec<usize>) -> Self {
        let mut offsets = Vec::new();
        let mut at = 0;
        for w in sizes.windows(2) {
            offsets.push((at, at + w[0] * w[1]));
            at += w[0] * w[1] + w[1];
        }
        let mut v = Collect(Vec::new());
        module.visit(&mut v);
        Self {
            sizes,
            params: v.0,
            offsets,
        }
    }

    pub(super) fn layers(&self) -> usize {
        self.sizes.len() - 1
    }

    /// Where the MLP's parameters end (log σ follows in the actor).
    pub(super) fn mlp_len(&self) -> usize {
        let l = self.layers();
        self.offsets[l - 1].1 + self.sizes[l]
    }
}

/// The widths of an MLP's layers, input first.
pub(super) fn mlp_widths(mlp: &crate::model::Mlp) -> Vec<usize> {
    let mut sizes = Vec::new();
    for (i, layer) in mlp.layers.iter().enumerate() {
        let [fan_in, fan_out] = layer.weight.val().dims();
        if i == 0 {
            sizes.push(fan_in);
        }
        sizes.push(fan_out);
    }
    sizes
}

/// Collects a module's float parameters, flattened in visiting order.
pub(super) struct Collect(Vec<f32>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.0.extend(values(param.val()));
    }
}

/// Overwrites a module's float parameters, in visiting order, from a flat slice (keeping
/// their ids and whether they require gradients).
pub(super) struct Overwrite<'a> {
    pub(super) values: &'a [f32],
    pub(super) at: usize,
}

impl ModuleMapper for Overwrite<'_> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let (id, tensor, mapper) = param.consume();
        let shape = tensor.dims();
        let n: usize = shape.iter().product();
        let data = self.values[self.at..self.at + n].to_vec();
        self.at += n;
        let mut t = Tensor::<D>::from_data(TensorData::new(data, shape), &tensor.device());
        if tensor.is_require_grad() {
            t = t.require_grad();
        }
        Param::from_mapped_value(id, t, mapper)
    }
}

/// One thread's buffers for a chunk: the gathered observations, the hidden activations
/// (after tanh), the outputs and two gradient buffers.
#[derive(Clone, Debug)]
pub(super) struct Workspace {
    pub(super) x: Vec<f32>,
    pub(super) hidden: Vec<Vec<f32>>,
    pub(super) y: Vec<f32>,
    pub(super) d_a: Vec<f32>,
    pub(super) d_b: Vec<f32>,
}

impl Workspace {
    pub(super) fn new(sizes: &[usize]) -> Self {
        let widest = sizes.iter().copied().max().unwrap_or(1);
        let l = sizes.len() - 1;
        Self {
            x: vec![0.0; CHUNK * sizes[0]],
            hidden: sizes[1..l].iter().map(|&w| vec![0.0; CHUNK * w]).collect(),
            y: vec![0.0; CHUNK * sizes[l]],
            d_a: vec![0.0; CHUNK * widest],
            d_b: vec![0.0; CHUNK * widest],
        }
    }
}

/// One network of the fused update: its parameters, gradients, Adam state and buffers.
#[derive(Clone, Debug)]
pub(super) struct Side {
    pub(super) net: FlatNet,
    pub(super) grad: Vec<f32>,
    pub(super) adam: AdamMoments,
    pub(super) ws: Workspace,
}

impl Side {
    pub(super) fn new(net: FlatNet, adam: Option<AdamMoments>) -> Self {
        let n = net.params.len();
        let adam = adam
            .filter(|a| a.moment_1.len() == n && a.moment_2.len() == n)
            .unwrap_or_else(|| AdamMoments::new(n));
        Self {
            grad: vec![0.0; n],
            ws: Workspace::new(&net.sizes),
            net,
            adam,
        }
    }

    /// The outputs for every row of `obs` (row-major, the network's input width), chunk by
    /// chunk.
    pub(super) fn outputs(&mut self, obs: &[f32]) -> Vec<f32> {
        let Self { net, ws, .. } = self;
        let (n_in, out) = (net.sizes[0], net.sizes[net.layers()]);
        let mut y = Vec::with_capacity(obs.len() / n_in * out);
        for rows in obs.chunks(CHUNK * n_in) {
            let m = rows.len() / n_in;
            ws.x[..m * n_in].copy_from_slice(&rows[..m * n_in]);
            forward(net, ws, m);
            y.extend_from_slice(&ws.y[..m * out]);
        }
        y
    }

    /// Forward and backward over the samples `idx` of `b`, chunk by chunk: `head` gets a
    /// chunk's sample indices and outputs `[m, out]` and writes d loss / d outputs. Leaves
    /// the MLP's gradients in `grad` (the tail past the MLP is the caller's).
    pub(super) fn pass(
        &mut self,
        b: &Batch,
        idx: &[usize],
        mut head: impl FnMut(&[usize], &[f32], &mut [f32]),
    ) {
        let Self { net, grad, ws, .. } = self;
        grad.fill(0.0);
        let sizes = &net.sizes;
        let layers = net.layers();
        let n_in = sizes[0];
        let out = sizes[layers];
        for rows in idx.chunks(CHUNK) {
            let m = rows.len();
            for (r, &i) in rows.iter().enumerate() {
                ws.x[r * n_in..(r + 1) * n_in].copy_from_slice(&b.obs[i * n_in..(i + 1) * n_in]);
            }
            forward(net, ws, m);
            // Loss head: d loss / d outputs into d_a.
            head(rows, &ws.y[..m * out], &mut ws.d_a[..m * out]);
            // Backward.
            for l in (0..layers).rev() {
                let (fi, fo) = (sizes[l], sizes[l + 1]);
                let (wo, bo) = net.offsets[l];
                let d = &ws.d_a[..m * fo];
                let gb = &mut grad[bo..bo + fo];
                for row in d.chunks_exact(fo) {
                    for (g, &x) in gb.iter_mut().zip(row) {
                        *g += x;
                    }
                }
                let input: &[f32] = if l == 0 { &ws.x } else { &ws.hidden[l - 1] };
                // dW[in, out] += inputᵀ · d
                gemm(
                    fi,
                    m,
                    fo,
                    &input[..m * fi],
                    (1, fi),
                    d,
                    (fo, 1),
                    1.0,
                    &mut grad[wo..wo + fi * fo],
                );
                if l > 0 {
                    // d_prev[m, in] = d · Wᵀ, then through tanh: × (1 − h²).
                    let w = &net.params[wo..wo + fi * fo];
                    let next = &mut ws.d_b[..m * fi];
                    gemm(m, fo, fi, d, (fo, 1), w, (1, fo), 0.0, next);
                    tanh_backward(next, &ws.hidden[l - 1][..m * fi]);
                    std::mem::swap(&mut ws.d_a, &mut ws.d_b);
                }
            }
        }
    }
}

/// The forward pass of the first `m` rows of `ws.x` through `net`: hidden activations into
/// `ws.hidden`, outputs into `ws.y`.
pub(super) fn forward(net: &FlatNet, ws: &mut Workspace, m: usize) {
    let sizes = &net.sizes;
    let layers = net.layers();
    for l in 0..layers {
        let (fi, fo) = (sizes[l], sizes[l + 1]);
        let (wo, bo) = net.offsets[l];
        let w = &net.params[wo..wo + fi * fo];
        let bias = &net.params[bo..bo + fo];
        let (before, after) = ws.hidden.split_at_mut(l.min(layers - 1));
        let input: &[f32] = if l == 0 { &ws.x } else { &before[l - 1] };
        let output: &mut [f32] = if l + 1 < layers {
            &mut after[0]
        } else {
            &mut ws.y
        };
        let output = &mut output[..m * fo];
        for row in output.chunks_exact_mut(fo) {
            row.copy_from_slice(bias);
        }
        gemm(
            m,
            fi,
            fo,
            &input[..m * fi],
            (fi, 1),
            w,
            (fo, 1),
            1.0,
            output,
        );
        if l + 1 < layers {
            tanh_in_place(output);
        }
    }
}
