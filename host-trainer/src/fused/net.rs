//! A feed-forward network as flat buffers: its parameters in `burn`'s visiting order, the
//! per-thread activations of a chunk, and the chunked forward and backward passes.

use super::kernels::{gemm, tanh_backward, tanh_in_place};
use super::lstm::Recurrent;
use super::{AdamMoments, CHUNK};
use crate::batch::{Batch, Minibatch};
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
    /// The parameters of `module` (an actor or a critic) whose MLP has layer widths `sizes`
    /// and starts at parameter `start` (after the LSTM layers of a recurrent network).
    pub(super) fn of<M: Module>(module: &M, sizes: Vec<usize>, start: usize) -> Self {
        let mut offsets = Vec::new();
        let mut at = start;
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
    /// The parameters, with the MLP's layout (the head of a recurrent network).
    pub(super) net: FlatNet,
    pub(super) grad: Vec<f32>,
    pub(super) adam: AdamMoments,
    pub(super) ws: Workspace,
    /// A recurrent network's LSTM layers (before the MLP in `net.params`).
    pub(super) recurrent: Option<Recurrent>,
    /// What a feed-forward network reads of a batch.
    pub(super) input: Input,
}

/// The rows a feed-forward [`Side`] reads of a batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Input {
    /// The actor's observations (`Batch::obs`).
    Observation,
    /// The privileged critic's states (`Batch::critic`).
    Privileged,
}

impl Input {
    /// The rows of `b` this input reads, one per sample (empty when `b` holds none).
    pub(super) fn rows(self, b: &Batch) -> &[f32] {
        match self {
            Self::Observation => &b.obs,
            Self::Privileged => b.critic.as_ref().map_or(&[][..], |c| &c.obs),
        }
    }

    /// The rows after the window, one per env, given the observations after it.
    pub(super) fn last_rows<'a>(self, b: &'a Batch, last_obs: &'a [f32]) -> &'a [f32] {
        match self {
            Self::Observation => last_obs,
            Self::Privileged => b.critic.as_ref().map_or(&[][..], |c| &c.last_obs),
        }
    }
}

/// Envs per group when a whole rollout's windows run forward ([`Side::window_outputs`]): the
/// tape of a group stays a few MB.
const ENV_GROUP: usize = 64;

impl Side {
    pub(super) fn new(
        net: FlatNet,
        adam: Option<AdamMoments>,
        recurrent: Option<Recurrent>,
        input: Input,
    ) -> Self {
        let n = net.params.len();
        let adam = adam
            .filter(|a| a.moment_1.len() == n && a.moment_2.len() == n)
            .unwrap_or_else(|| AdamMoments::new(n));
        Self {
            grad: vec![0.0; n],
            ws: Workspace::new(&net.sizes),
            net,
            adam,
            recurrent,
            input,
        }
    }

    /// A recurrent network's outputs for every sample of `b` (its windows from the stored
    /// states); with `last_obs` (the observations after the window) also the outputs for
    /// those and the states to start the next window from (after the last step, zeroed
    /// where the episode ended there), else both empty. Empty for a feed-forward network.
    pub(super) fn window_outputs(
        &mut self,
        b: &Batch,
        last_obs: Option<&[f32]>,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let Self {
            net, ws, recurrent, ..
        } = self;
        let (Some(rec), Some(seq)) = (recurrent, &b.sequence) else {
            return (Vec::new(), Vec::new(), Vec::new());
        };
        let (envs, out, d) = (seq.num_envs, net.sizes[net.layers()], b.obs_dim);
        let width = rec.layout.state_width();
        let mut y = vec![0.0; b.obs.len() / d.max(1) * out];
        let (mut last, mut next) = match last_obs {
            Some(_) => (vec![0.0; envs * out], vec![0.0; envs * width]),
            None => (Vec::new(), Vec::new()),
        };
        let mut state = Vec::new();
        let all: Vec<usize> = (0..envs).collect();
        for group in all.chunks(ENV_GROUP) {
            let mb = Minibatch::of_envs(b, group);
            rec.load_windows(b, &mb);
            rec.tape.forward(&net.params, &rec.layout);
            head_outputs(net, ws, rec.tape.top(), |row, v| {
                let i = mb.samples[row];
                y[i * out..(i + 1) * out].copy_from_slice(v);
            });
            let Some(last_obs) = last_obs else {
                continue;
            };
            // One more step, on the observations after the window.
            rec.tape.final_state(&rec.layout, &mut state);
            let tape = &mut rec.tape;
            tape.begin(&rec.layout, group.len(), 1);
            for (j, &env) in group.iter().enumerate() {
                let k = seq.last_keep[env];
                tape.x.extend_from_slice(&last_obs[env * d..(env + 1) * d]);
                tape.keep.push(k);
                for (n, &s) in next[env * width..(env + 1) * width]
                    .iter_mut()
                    .zip(&state[j * width..(j + 1) * width])
                {
                    *n = s * k;
                }
            }
            tape.init.extend_from_slice(&state);
            tape.forward(&net.params, &rec.layout);
            head_outputs(net, ws, tape.top(), |row, v| {
                let env = group[row];
                last[env * out..(env + 1) * out].copy_from_slice(v);
            });
        }
        (y, last, next)
    }

    /// The outputs for every sample of `b` and, with `last_obs` (the observations after the
    /// window), for the states after the window and (a recurrent network) its states to
    /// start the next window from; a feed-forward network reads its [`Input`].
    pub(super) fn batch_outputs(
        &mut self,
        b: &Batch,
        last_obs: Option<&[f32]>,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        if self.recurrent.is_some() {
            return self.window_outputs(b, last_obs);
        }
        let input = self.input;
        let all = self.outputs(input.rows(b));
        let last = last_obs.map_or_else(Vec::new, |l| self.outputs(input.last_rows(b, l)));
        (all, last, Vec::new())
    }

    /// The outputs for every row of `obs` (row-major, the network's input width), chunk by
    /// chunk (feed-forward networks).
    pub(super) fn outputs(&mut self, obs: &[f32]) -> Vec<f32> {
        let Self { net, ws, .. } = self;
        let (n_in, out) = (net.sizes[0], net.sizes[net.layers()]);
        let mut y = Vec::with_capacity(obs.len() / n_in * out);
        head_outputs(net, ws, obs, |_, v| y.extend_from_slice(v));
        y
    }

    /// Forward and backward over the samples of `mb`, chunk by chunk: `head` gets a chunk's
    /// sample indices and outputs `[m, out]` and writes d loss / d outputs. Leaves the
    /// network's gradients in `grad` (the tail past the MLP is the caller's). A recurrent
    /// network runs `mb`'s whole windows through its LSTM layers first and backpropagates
    /// through time after the head.
    pub(super) fn pass(
        &mut self,
        b: &Batch,
        mb: &Minibatch,
        mut head: impl FnMut(&[usize], &[f32], &mut [f32]),
    ) {
        let Self {
            net,
            grad,
            ws,
            recurrent,
            input,
            ..
        } = self;
        grad.fill(0.0);
        let out = net.sizes[net.layers()];
        let n_in = net.sizes[0];
        let Some(rec) = recurrent else {
            let source = input.rows(b);
            if source.len() < b.len() * n_in {
                // A batch without this network's input (a privileged critic on a rollout
                // that recorded no privileged state): no gradient.
                return;
            }
            for rows in mb.samples.chunks(CHUNK) {
                let m = rows.len();
                for (r, &i) in rows.iter().enumerate() {
                    ws.x[r * n_in..(r + 1) * n_in]
                        .copy_from_slice(&source[i * n_in..(i + 1) * n_in]);
                }
                forward(net, ws, m);
                head(rows, &ws.y[..m * out], &mut ws.d_a[..m * out]);
                backward(net, ws, grad, m, false);
            }
            return;
        };
        if !rec.load_windows(b, mb) {
            return;
        }
        let Recurrent { layout, tape, .. } = rec;
        tape.forward(&net.params, layout);
        let hidden = layout.hidden;
        let mut d_top = std::mem::take(&mut tape.d_top);
        d_top.resize(tape.rows() * hidden, 0.0);
        for (k, rows) in mb.samples.chunks(CHUNK).enumerate() {
            let (m, at) = (rows.len(), k * CHUNK * hidden);
            ws.x[..m * hidden].copy_from_slice(&tape.top()[at..at + m * hidden]);
            forward(net, ws, m);
            head(rows, &ws.y[..m * out], &mut ws.d_a[..m * out]);
            backward(net, ws, grad, m, true);
            d_top[at..at + m * hidden].copy_from_slice(&ws.d_a[..m * hidden]);
        }
        tape.d_top = d_top;
        tape.backward(&net.params, layout, grad);
    }
}

/// The backward pass through `net` of the chunk last run by [`forward`] (`m` rows), from
/// d loss / d outputs in `ws.d_a`: adds the weight gradients into `grad`; with `to_input`
/// leaves d loss / d inputs in `ws.d_a` (`[m, in]`).
pub(super) fn backward(
    net: &FlatNet,
    ws: &mut Workspace,
    grad: &mut [f32],
    m: usize,
    to_input: bool,
) {
    let sizes = &net.sizes;
    for l in (0..net.layers()).rev() {
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
        if l > 0 || to_input {
            // d_prev[m, in] = d · Wᵀ, then through tanh: × (1 − h²).
            let w = &net.params[wo..wo + fi * fo];
            let next = &mut ws.d_b[..m * fi];
            gemm(m, fo, fi, d, (fo, 1), w, (1, fo), 0.0, next);
            if l > 0 {
                tanh_backward(next, &ws.hidden[l - 1][..m * fi]);
            }
            std::mem::swap(&mut ws.d_a, &mut ws.d_b);
        }
    }
}

/// The head (`net`) on every row of `input`, chunk by chunk: `put(row, outputs)`.
fn head_outputs(
    net: &FlatNet,
    ws: &mut Workspace,
    input: &[f32],
    mut put: impl FnMut(usize, &[f32]),
) {
    let (n_in, out) = (net.sizes[0], net.sizes[net.layers()]);
    for (k, rows) in input.chunks(CHUNK * n_in).enumerate() {
        let m = rows.len() / n_in;
        ws.x[..m * n_in].copy_from_slice(&rows[..m * n_in]);
        forward(net, ws, m);
        for (r, v) in ws.y[..m * out].chunks_exact(out).enumerate() {
            put(k * CHUNK + r, v);
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
