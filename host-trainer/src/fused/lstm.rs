//! The LSTM layers of the recurrent rows (E, F, G) in the fused update: forward over whole
//! env windows from stored states, and backpropagation through time over the window.
//!
//! **Layout.** Time-major, as the batch stores a window: row `t·E + e` is env `e`'s step
//! `t`. Per layer the input side is one GEMM over the whole window (`[T·E, in] × [in, 4H]`
//! plus the bias); the recurrent side is one GEMM per step for all envs (`[E, H] × [H, 4H]`),
//! then the gates and the cell elementwise (PyTorch's gate blocks i, f, g, o;
//! [`crate::recurrent::FusedLstm`]'s parameters, flat in `burn`'s order: `weight_ih`
//! `[in, 4H]`, `weight_hh` `[H, 4H]`, `bias` `[4H]`).
//!
//! **Episode ends.** Before step `t` an env's `h` and `c` are multiplied by `keep[t]` (0
//! where its episode ended at step `t − 1`), as [`crate::recurrent::LstmNet::sequence`]
//! does; the backward pass multiplies the gradient flowing to the step before by the same
//! mask, so nothing flows across an episode end.
//!
//! **Backward.** The tape keeps every step's gate activations, cells, `tanh(c)`, outputs
//! and masked previous states. Going back in time per step: the cell's gradient
//! elementwise, then `dh_prev = dz · W_hhᵀ` (one GEMM for all envs). The weight gradients
//! are then one GEMM each over the whole window (`xᵀ · dz`, `h_prevᵀ · dz`), and the
//! gradient for the layer below `dz · W_ihᵀ`. No allocation once the buffers have grown to
//! the window's size.

use super::kernels::{gemm, lstm_cell_backward, lstm_cell_forward};
use crate::batch::{Batch, Minibatch};

/// Where one LSTM layer's parameters are in the flat vector.
#[derive(Clone, Copy, Debug)]
pub(super) struct LayerAt {
    /// Input width.
    pub(super) input: usize,
    /// Offset of `weight_ih` `[in, 4H]`.
    pub(super) w_ih: usize,
    /// Offset of `weight_hh` `[H, 4H]`.
    pub(super) w_hh: usize,
    /// Offset of `bias` `[4H]`.
    pub(super) bias: usize,
}

/// The LSTM layers' places in the flat parameters (they come first, in `burn`'s order).
#[derive(Clone, Debug)]
pub(super) struct LstmLayout {
    /// Hidden size H.
    pub(super) hidden: usize,
    /// The layers, input side first.
    pub(super) layers: Vec<LayerAt>,
}

impl LstmLayout {
    /// `layers` layers of `hidden` on an `input`-wide observation.
    pub(super) fn new(input: usize, hidden: usize, layers: usize) -> Self {
        let mut at = 0;
        let mut width = input;
        let layers = (0..layers)
            .map(|_| {
                let l = LayerAt {
                    input: width,
                    w_ih: at,
                    w_hh: at + width * 4 * hidden,
                    bias: at + width * 4 * hidden + hidden * 4 * hidden,
                };
                at = l.bias + 4 * hidden;
                width = hidden;
                l
            })
            .collect();
        Self { hidden, layers }
    }

    /// Parameters of the LSTM layers (the head's start).
    pub(super) fn len(&self) -> usize {
        self.layers.last().map_or(0, |l| l.bias + 4 * self.hidden)
    }

    /// Values of one env's state: per layer `h` then `c` ([`crate::recurrent::LstmState`]'s
    /// flat order).
    pub(super) fn state_width(&self) -> usize {
        2 * self.layers.len() * self.hidden
    }
}

/// One layer's record of a window's forward pass (each `[T·E, ·]`, time-major).
#[derive(Clone, Debug, Default)]
struct LayerTape {
    /// Gate activations σ(i), σ(f), tanh(g), σ(o), `[·, 4H]`.
    gates: Vec<f32>,
    /// Cells.
    c: Vec<f32>,
    /// tanh of the cells.
    tc: Vec<f32>,
    /// Outputs (the next layer's input).
    h: Vec<f32>,
    /// The masked states each step starts from.
    h_prev: Vec<f32>,
    /// The masked cells each step starts from.
    c_prev: Vec<f32>,
}

/// A window's forward record and the backward pass's buffers, grown once and reused.
#[derive(Clone, Debug, Default)]
pub(super) struct Tape {
    /// Envs E.
    envs: usize,
    /// Steps T.
    steps: usize,
    /// The first layer's input, `[T·E, in]` (filled by the caller, see [`Tape::begin`]).
    pub(super) x: Vec<f32>,
    /// `[T·E]`: 0 where the env's state is zeroed before the step.
    pub(super) keep: Vec<f32>,
    /// The states the window starts from, `[E, state width]` (all zero when empty).
    pub(super) init: Vec<f32>,
    layers: Vec<LayerTape>,
    /// d loss / d the top layer's outputs on entry to the backward pass, `[T·E, H]`.
    pub(super) d_top: Vec<f32>,
    d_z: Vec<f32>,
    d_below: Vec<f32>,
    d_h: Vec<f32>,
    d_c: Vec<f32>,
}

/// `v` at length `n`, zero-filled where it grows.
fn sized(v: &mut Vec<f32>, n: usize) {
    v.resize(n, 0.0);
}

impl Tape {
    /// Sizes the tape for `envs` envs over `steps` steps; the caller then fills `x`
    /// (`[T·E, input]`), `keep` and `init`.
    pub(super) fn begin(&mut self, layout: &LstmLayout, envs: usize, steps: usize) {
        let (n, h) = (envs * steps, layout.hidden);
        self.envs = envs;
        self.steps = steps;
        let input = layout.layers.first().map_or(0, |l| l.input);
        self.x.clear();
        self.x.reserve(n * input);
        self.keep.clear();
        self.init.clear();
        self.layers
            .resize_with(layout.layers.len(), LayerTape::default);
        for l in &mut self.layers {
            sized(&mut l.gates, n * 4 * h);
            for v in [&mut l.c, &mut l.tc, &mut l.h, &mut l.h_prev, &mut l.c_prev] {
                sized(v, n * h);
            }
        }
    }

    /// Rows T·E.
    pub(super) fn rows(&self) -> usize {
        self.envs * self.steps
    }

    /// The top layer's outputs, `[T·E, H]`.
    pub(super) fn top(&self) -> &[f32] {
        self.layers.last().map_or(&[], |l| &l.h)
    }

    /// The state after the window's last step, `[E, state width]` (not masked).
    pub(super) fn final_state(&self, layout: &LstmLayout, out: &mut Vec<f32>) {
        let (e, h) = (self.envs, layout.hidden);
        out.clear();
        if self.steps == 0 {
            out.extend_from_slice(&self.init);
            return;
        }
        let last = (self.steps - 1) * e;
        for env in 0..e {
            for l in &self.layers {
                let row = (last + env) * h..(last + env + 1) * h;
                out.extend_from_slice(&l.h[row.clone()]);
                out.extend_from_slice(&l.c[row]);
            }
        }
    }

    /// Runs the window through the LSTM layers of `params` (see the module doc).
    pub(super) fn forward(&mut self, params: &[f32], layout: &LstmLayout) {
        let (e, steps, h) = (self.envs, self.steps, layout.hidden);
        let (n, width) = (e * steps, layout.state_width());
        let g = 4 * h;
        for (li, at) in layout.layers.iter().enumerate() {
            let (below, rest) = self.layers.split_at_mut(li);
            let tape = &mut rest[0];
            let x: &[f32] = match below.last() {
                Some(prev) => &prev.h,
                None => &self.x,
            };
            let w_ih = &params[at.w_ih..at.w_ih + at.input * g];
            let w_hh = &params[at.w_hh..at.w_hh + h * g];
            let bias = &params[at.bias..at.bias + g];
            for row in tape.gates[..n * g].chunks_exact_mut(g) {
                row.copy_from_slice(bias);
            }
            gemm(
                n,
                at.input,
                g,
                &x[..n * at.input],
                (at.input, 1),
                w_ih,
                (g, 1),
                1.0,
                &mut tape.gates,
            );
            for t in 0..steps {
                let rows = t * e..(t + 1) * e;
                // The masked state this step starts from.
                for (env, &k) in self.keep[rows.clone()].iter().enumerate() {
                    let r = (t * e + env) * h..(t * e + env + 1) * h;
                    let (hp, cp) = (&mut tape.h_prev[r.clone()], &mut tape.c_prev[r]);
                    if t == 0 {
                        let s = env * width + 2 * li * h;
                        match self.init.get(s..s + 2 * h) {
                            Some(state) => {
                                let (h0, c0) = state.split_at(h);
                                hp.iter_mut().zip(h0).for_each(|(a, &b)| *a = b * k);
                                cp.iter_mut().zip(c0).for_each(|(a, &b)| *a = b * k);
                            }
                            None => {
                                hp.fill(0.0);
                                cp.fill(0.0);
                            }
                        }
                    } else {
                        let p = ((t - 1) * e + env) * h..((t - 1) * e + env) * h + h;
                        hp.iter_mut()
                            .zip(&tape.h[p.clone()])
                            .for_each(|(a, &b)| *a = b * k);
                        cp.iter_mut().zip(&tape.c[p]).for_each(|(a, &b)| *a = b * k);
                    }
                }
                let (hr, gr) = (rows.start * h..rows.end * h, rows.start * g..rows.end * g);
                gemm(
                    e,
                    h,
                    g,
                    &tape.h_prev[hr.clone()],
                    (h, 1),
                    w_hh,
                    (g, 1),
                    1.0,
                    &mut tape.gates[gr.clone()],
                );
                lstm_cell_forward(
                    &mut tape.gates[gr],
                    &tape.c_prev[hr.clone()],
                    &mut tape.c[hr.clone()],
                    &mut tape.tc[hr.clone()],
                    &mut tape.h[hr],
                    h,
                );
            }
        }
    }

    /// Backpropagation through time over the window last run by [`Tape::forward`], from
    /// `d_top` (d loss / d the top layer's outputs): adds the LSTM layers' gradients into
    /// `grad` (flat, as `params`). The gradients for the observations and the initial state
    /// are not formed (they are data).
    pub(super) fn backward(&mut self, params: &[f32], layout: &LstmLayout, grad: &mut [f32]) {
        let (e, steps, h) = (self.envs, self.steps, layout.hidden);
        let n = e * steps;
        let g = 4 * h;
        sized(&mut self.d_z, n * g);
        sized(&mut self.d_h, e * h);
        sized(&mut self.d_c, e * h);
        for (li, at) in layout.layers.iter().enumerate().rev() {
            let w_ih = &params[at.w_ih..at.w_ih + at.input * g];
            let w_hh = &params[at.w_hh..at.w_hh + h * g];
            let tape = &self.layers[li];
            self.d_h.fill(0.0);
            self.d_c.fill(0.0);
            for t in (0..steps).rev() {
                let (hr, gr) = (t * e * h..(t + 1) * e * h, t * e * g..(t + 1) * e * g);
                for (d, &y) in self.d_h.iter_mut().zip(&self.d_top[hr.clone()]) {
                    *d += y;
                }
                lstm_cell_backward(
                    &tape.gates[gr.clone()],
                    &tape.c_prev[hr.clone()],
                    &tape.tc[hr],
                    &self.d_h,
                    &mut self.d_c,
                    &mut self.d_z[gr.clone()],
                    h,
                );
                if t == 0 {
                    break;
                }
                // dh_prev = dz · W_hhᵀ, then the masks of this step.
                gemm(
                    e,
                    g,
                    h,
                    &self.d_z[gr],
                    (g, 1),
                    w_hh,
                    (1, g),
                    0.0,
                    &mut self.d_h,
                );
                let keep = &self.keep[t * e..(t + 1) * e];
                for ((dh, dc), &k) in self
                    .d_h
                    .chunks_exact_mut(h)
                    .zip(self.d_c.chunks_exact_mut(h))
                    .zip(keep)
                {
                    dh.iter_mut().for_each(|d| *d *= k);
                    dc.iter_mut().for_each(|d| *d *= k);
                }
            }
            let d_z = &self.d_z[..n * g];
            let x: &[f32] = match li.checked_sub(1) {
                Some(below) => &self.layers[below].h,
                None => &self.x,
            };
            // dW_ih += xᵀ · dz, dW_hh += h_prevᵀ · dz, d bias += Σ dz.
            gemm(
                at.input,
                n,
                g,
                &x[..n * at.input],
                (1, at.input),
                d_z,
                (g, 1),
                1.0,
                &mut grad[at.w_ih..at.w_ih + at.input * g],
            );
            gemm(
                h,
                n,
                g,
                &tape.h_prev[..n * h],
                (1, h),
                d_z,
                (g, 1),
                1.0,
                &mut grad[at.w_hh..at.w_hh + h * g],
            );
            let d_bias = &mut grad[at.bias..at.bias + g];
            for row in d_z.chunks_exact(g) {
                d_bias.iter_mut().zip(row).for_each(|(a, &b)| *a += b);
            }
            if li > 0 {
                // d loss / d the layer below's outputs: dz · W_ihᵀ.
                sized(&mut self.d_below, n * at.input);
                gemm(
                    n,
                    g,
                    at.input,
                    d_z,
                    (g, 1),
                    w_ih,
                    (1, g),
                    0.0,
                    &mut self.d_below,
                );
                std::mem::swap(&mut self.d_top, &mut self.d_below);
            }
        }
    }
}

/// Which of the window's stored states a network starts from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Role {
    /// [`crate::batch::Sequences::actor_h0`].
    Actor,
    /// [`crate::batch::Sequences::critic_h0`].
    Critic,
}

/// The LSTM part of a recurrent network in the fused update.
#[derive(Clone, Debug)]
pub(super) struct Recurrent {
    pub(super) layout: LstmLayout,
    pub(super) tape: Tape,
    pub(super) role: Role,
}

impl Recurrent {
    pub(super) fn new(layout: LstmLayout, role: Role) -> Self {
        Self {
            layout,
            tape: Tape::default(),
            role,
        }
    }

    /// Loads the windows of `mb` (its envs' observations, masks and starting states) into
    /// the tape; false when `b` has no windows.
    pub(super) fn load_windows(&mut self, b: &Batch, mb: &Minibatch) -> bool {
        let Some(seq) = &b.sequence else {
            return false;
        };
        let Self { layout, tape, role } = self;
        let d = b.obs_dim;
        tape.begin(layout, mb.envs.len(), seq.steps);
        for &i in &mb.samples {
            tape.x.extend_from_slice(&b.obs[i * d..(i + 1) * d]);
            tape.keep.push(seq.keep[i]);
        }
        let h0 = match role {
            Role::Actor => &seq.actor_h0,
            Role::Critic => &seq.critic_h0,
        };
        let w = layout.state_width();
        if !h0.is_empty() {
            for &env in &mb.envs {
                tape.init.extend_from_slice(&h0[env * w..(env + 1) * w]);
            }
        }
        true
    }
}
