//! The recurrent Table 1 networks (rows E, F, G) on `burn`: a stack of LSTM layers, then an
//! MLP head with tanh hidden layers and a linear output, for the actor (4 Gaussian means
//! and a learned log σ) and the critic (one value). They are what recurrent PPO trains:
//! [`crate::ppo`] runs them through the [`PpoNet`] implementations at the end of this file,
//! which run a minibatch's whole env windows from the states stored at rollout time.
//!
//! **The fused cell.** Each layer keeps its four gates in one input weight `[in, 4H]` and
//! one recurrent weight `[H, 4H]` (PyTorch's gate order i, f, g, o along the columns), so a
//! step is one `[B, in] × [in, 4H]` and one `[B, H] × [H, 4H]` matmul; `burn`'s `nn::Lstm` runs a linear
//! per gate (issue "stage2": about 2× slower to train). tanh is `2·σ(2x) − 1` as in
//! [`crate::model`].
//!
//! **Payload order** is firmware-core's (`firmware_core::nn`): per LSTM layer `weight_ih`
//! `[4H][in]` row-major, `weight_hh` `[4H][H]`, then one bias `[4H]` holding PyTorch's
//! `bias_ih + bias_hh`; then the head's layers, weight `[out][in]` and bias. The export
//! transposes `burn`'s `[in, out]` layout. Parity with firmware-core's `Policy` is tested in
//! `host-trainer/tests/recurrent.rs`.
//!
//! **Sequences and episode ends.** [`LstmNet::sequence`] runs `T` steps of `B` envs from a
//! stored initial state and zeroes an env's state before step `t` when its episode ended at
//! step `t − 1` (`keep[t] = 0`), as the controller does at a respawn. Over a rollout window
//! this computes exactly what RSL-RL's split-at-dones-and-pad does: each trajectory starts
//! from the state stored at its first step (zero after a reset), and a padded step is one
//! that does not exist here; the test checks the two against each other.

use crate::batch::{Batch, Minibatch, gather, tensor2};
use crate::model::{Mlp, fast_tanh, values};
use crate::nets::{PolicyNet, PpoNet, ValueNet};
use burn::module::{Module, Param};
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::policy::{Architecture, TensorKind};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// One LSTM layer with its four gates fused (see the module doc).
#[derive(Module, Debug)]
pub struct FusedLstm {
    /// Input weights, `[in, 4H]`, gate blocks i, f, g, o along the columns.
    pub weight_ih: Param<Tensor<2>>,
    /// Recurrent weights, `[H, 4H]`.
    pub weight_hh: Param<Tensor<2>>,
    /// `bias_ih + bias_hh`, `[4H]`.
    pub bias: Param<Tensor<1>>,
}

impl FusedLstm {
    /// Hidden size H.
    pub fn hidden(&self) -> usize {
        self.weight_hh.val().dims()[0]
    }

    /// Initialised as PyTorch's `nn.LSTM`: every weight and both biases uniform in ±1/√H,
    /// drawn in PyTorch's parameter order (`weight_ih`, `weight_hh`, `bias_ih`, `bias_hh`,
    /// each `[4H, ·]` row-major); the stored bias is the sum of the two.
    pub fn new(input: usize, hidden: usize, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let bound = 1.0 / (hidden as f32).sqrt();
        let mut draw =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-bound..bound)).collect() };
        let w_ih = draw(4 * hidden * input);
        let w_hh = draw(4 * hidden * hidden);
        let b_ih = draw(4 * hidden);
        let b_hh = draw(4 * hidden);
        let bias: Vec<f32> = b_ih.iter().zip(&b_hh).map(|(a, b)| a + b).collect();
        Self::from_pytorch(&w_ih, &w_hh, &bias, input, hidden, device)
    }

    /// From PyTorch-layout weights (`[4H][in]`, `[4H][H]` row-major) and the summed bias.
    pub fn from_pytorch(
        w_ih: &[f32],
        w_hh: &[f32],
        bias: &[f32],
        input: usize,
        hidden: usize,
        device: &Device,
    ) -> Self {
        let t = |w: &[f32], cols: usize| {
            Tensor::<2>::from_data(TensorData::new(w.to_vec(), [4 * hidden, cols]), device)
                .transpose()
        };
        Self {
            weight_ih: Param::from_tensor(t(w_ih, input)),
            weight_hh: Param::from_tensor(t(w_hh, hidden)),
            bias: Param::from_tensor(Tensor::from_data(
                TensorData::new(bias.to_vec(), [4 * hidden]),
                device,
            )),
        }
    }

    /// One step from the input side's pre-activations `zx = x W_ih + b` (`[B, 4H]`):
    /// `(h, c) → (h', c')`.
    fn step(&self, zx: Tensor<2>, h: Tensor<2>, c: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let z = zx + h.matmul(self.weight_hh.val());
        let mut gates = z.chunk(4, 1).into_iter();
        let (Some(i), Some(f), Some(g), Some(o)) =
            (gates.next(), gates.next(), gates.next(), gates.next())
        else {
            unreachable!("chunk(4) of a 4H-wide tensor gives four blocks")
        };
        let c = sigmoid(f) * c + sigmoid(i) * fast_tanh(g);
        let h = sigmoid(o) * fast_tanh(c.clone());
        (h, c)
    }
}

/// The recurrent state of an [`LstmNet`] for `B` envs: per layer `h` and `c`, `[B, H]`.
#[derive(Clone, Debug)]
pub struct LstmState {
    /// `(h, c)` per layer, the first layer first.
    pub layers: Vec<(Tensor<2>, Tensor<2>)>,
}

impl LstmState {
    /// Values per env in the flat layout: per layer `h` then `c`, the first layer first
    /// (firmware-core's `LstmStackState` order: `first.h`, `first.c`, `deep[0].h`, …).
    pub fn width(layers: usize, hidden: usize) -> usize {
        2 * layers * hidden
    }

    /// A state from flat rows (`[B][width]`, see [`LstmState::width`]).
    pub fn from_flat(flat: &[f32], layers: usize, hidden: usize, device: &Device) -> Self {
        let width = Self::width(layers, hidden);
        let b = flat.len() / width.max(1);
        let all = Tensor::<2>::from_data(TensorData::new(flat.to_vec(), [b, width]), device);
        let layers = (0..layers)
            .map(|l| {
                (
                    all.clone().narrow(1, 2 * l * hidden, hidden),
                    all.clone().narrow(1, (2 * l + 1) * hidden, hidden),
                )
            })
            .collect();
        Self { layers }
    }

    /// The flat rows of this state (see [`LstmState::from_flat`]).
    pub fn to_flat(&self) -> Vec<f32> {
        let parts: Vec<Tensor<2>> = self
            .layers
            .iter()
            .flat_map(|(h, c)| [h.clone(), c.clone()])
            .collect();
        if parts.is_empty() {
            return Vec::new();
        }
        values(Tensor::cat(parts, 1))
    }
}

/// LSTM layers, then an MLP head (tanh hidden layers, linear output).
#[derive(Module, Debug)]
pub struct LstmNet {
    /// The LSTM layers, input side first.
    pub lstm: Vec<FusedLstm>,
    /// The head on the top layer's hidden state.
    pub head: Mlp,
}

impl LstmNet {
    /// A fresh network of `arch` (recurrent) with `outputs` outputs, initialised as
    /// PyTorch's modules from `rng`.
    pub fn new(arch: &Architecture, outputs: usize, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let hidden = usize::from(arch.lstm_hidden);
        let mut input = usize::from(arch.obs_dim);
        let mut lstm = Vec::new();
        for _ in 0..arch.lstm_layers {
            lstm.push(FusedLstm::new(input, hidden, rng, device));
            input = hidden;
        }
        let sizes: Vec<usize> = core::iter::once(hidden)
            .chain(arch.mlp_hidden.iter().map(|&w| usize::from(w)))
            .chain(core::iter::once(outputs))
            .collect();
        Self {
            lstm,
            head: Mlp::new(&sizes, rng, device),
        }
    }

    /// LSTM hidden size.
    pub fn hidden(&self) -> usize {
        self.lstm.first().map_or(0, FusedLstm::hidden)
    }

    /// A zero state for `envs` envs.
    pub fn zero_state(&self, envs: usize, device: &Device) -> LstmState {
        let h = self.hidden();
        LstmState {
            layers: self
                .lstm
                .iter()
                .map(|_| {
                    (
                        Tensor::zeros([envs, h], device),
                        Tensor::zeros([envs, h], device),
                    )
                })
                .collect(),
        }
    }

    /// Runs `obs` (`[T, B, in]`, time-major) from `state`; before step `t` each env's state
    /// is multiplied by `keep[t]` (`[T, B]`: 0 where its episode ended at step `t − 1`, else
    /// 1). Returns the head's outputs `[T·B, out]` (row `t·B + b`) and the state after the
    /// last step.
    pub fn sequence(
        &self,
        obs: Tensor<3>,
        keep: Tensor<2>,
        state: LstmState,
    ) -> (Tensor<2>, LstmState) {
        let [steps, envs, input] = obs.dims();
        // Per-step pieces, sliced from tensors that need no gradient (the observations and
        // the masks): slicing one large tensor that does (a whole window's input-side
        // pre-activations) costs a window-sized zero tensor per slice in the backward pass,
        // which made the whole update 5.8x slower (docs/PERFORMANCE.md).
        let mut xs: Vec<Tensor<2>> = obs
            .reshape([steps * envs, input])
            .split(envs, 0)
            .into_iter()
            .collect();
        let keeps: Vec<Tensor<2>> = keep
            .reshape([steps * envs, 1])
            .split(envs, 0)
            .into_iter()
            .collect();
        let mut layers = state.layers;
        for (layer, cell) in self.lstm.iter().enumerate() {
            let (w_ih, bias) = (cell.weight_ih.val(), cell.bias.val().unsqueeze::<2>());
            let (mut h, mut c) = layers[layer].clone();
            let mut outputs = Vec::with_capacity(steps);
            for (x_t, keep_t) in xs.iter().zip(&keeps) {
                h = h * keep_t.clone();
                c = c * keep_t.clone();
                let zx = x_t.clone().matmul(w_ih.clone()) + bias.clone();
                (h, c) = cell.step(zx, h, c);
                outputs.push(h.clone());
            }
            layers[layer] = (h, c);
            xs = outputs;
        }
        (self.head.forward(Tensor::cat(xs, 0)), LstmState { layers })
    }

    /// The weights in firmware-core payload order (see the module doc).
    pub fn payload(&self) -> Vec<f32> {
        let mut out = Vec::new();
        for cell in &self.lstm {
            out.extend(values(cell.weight_ih.val().transpose()));
            out.extend(values(cell.weight_hh.val().transpose()));
            out.extend(values(cell.bias.val()));
        }
        for layer in &self.head.layers {
            out.extend(values(layer.weight.val().transpose()));
            if let Some(b) = &layer.bias {
                out.extend(values(b.val()));
            }
        }
        out
    }

    /// The network holding `payload` (firmware-core order) for `arch` (recurrent), or `None`
    /// when the sizes do not match.
    pub fn from_payload(arch: &Architecture, payload: &[f32], device: &Device) -> Option<Self> {
        if !arch.is_recurrent() || payload.len() != arch.param_count() {
            return None;
        }
        let hidden = usize::from(arch.lstm_hidden);
        let mut offset = 0;
        let mut take = |n: usize| -> Option<&[f32]> {
            let v = payload.get(offset..offset + n)?;
            offset += n;
            Some(v)
        };
        let tensors = arch.tensors();
        let mut lstm = Vec::new();
        let mut head = Vec::new();
        for (i, t) in tensors.iter().enumerate() {
            match t.kind {
                TensorKind::LstmWeightIh(_) => {
                    let w_ih = take(t.len())?;
                    let w_hh = take(tensors.get(i + 1)?.len())?;
                    let bias = take(tensors.get(i + 2)?.len())?;
                    lstm.push(FusedLstm::from_pytorch(
                        w_ih, w_hh, bias, t.cols, hidden, device,
                    ));
                }
                TensorKind::LinearWeight(_) => {
                    let w = take(t.len())?;
                    let b = take(tensors.get(i + 1)?.len())?;
                    head.push(crate::model::linear_from_pytorch(
                        w, b, t.cols, t.rows, device,
                    ));
                }
                _ => {}
            }
        }
        Some(Self {
            lstm,
            head: Mlp { layers: head },
        })
    }
}

/// The recurrent Gaussian policy: an [`LstmNet`] giving the mean, and a learned
/// state-independent log σ.
#[derive(Module, Debug)]
pub struct RecurrentActor {
    /// Mean network.
    pub net: LstmNet,
    /// log σ per action.
    pub log_std: Param<Tensor<1>>,
}

/// The recurrent value function: an [`LstmNet`] with one output.
#[derive(Module, Debug)]
pub struct RecurrentCritic {
    /// Value network.
    pub net: LstmNet,
}

/// [`PpoNet`] for an LSTM network in field `net` whose window states are the batch's
/// `Sequences::$h0`: minibatches are whole env windows.
macro_rules! lstm_ppo_net {
    ($net:ty, $h0:ident) => {
        impl PpoNet for $net {
            const RECURRENT: bool = true;
            fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
                let h0 = b.sequence.as_ref().map_or(&[][..], |s| &s.$h0);
                window_outputs(&self.net, b, mb, h0, device)
            }
            fn rollout_outputs(
                &self,
                b: &Batch,
                last: Option<&[f32]>,
                device: &Device,
            ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
                let h0 = b.sequence.as_ref().map_or(&[][..], |s| &s.$h0);
                window_rollout_outputs(&self.net, b, last, h0, device)
            }
        }
    };
}

/// The windows of `mb.envs` through `net` from the states `h0` (`envs × width` rows of
/// the whole batch).
fn window_outputs(
    net: &LstmNet,
    b: &Batch,
    mb: &Minibatch,
    h0: &[f32],
    device: &Device,
) -> Tensor<2> {
    let Some(seq) = &b.sequence else {
        return Tensor::zeros([0, 1], device);
    };
    let (layers, hidden) = (net.lstm.len(), net.hidden());
    let width = LstmState::width(layers, hidden);
    let envs = mb.envs.len();
    let obs = tensor2(gather(&b.obs, b.obs_dim, &mb.samples), b.obs_dim, device)
        .reshape([seq.steps, envs, b.obs_dim]);
    let keep: Vec<f32> = mb.samples.iter().map(|&i| seq.keep[i]).collect();
    let keep = Tensor::<2>::from_data(TensorData::new(keep, [seq.steps, envs]), device);
    let state = if h0.is_empty() {
        net.zero_state(envs, device)
    } else {
        LstmState::from_flat(&gather(h0, width, &mb.envs), layers, hidden, device)
    };
    net.sequence(obs, keep, state).0
}

/// The whole rollout through `net` (no autodiff): every sample's output and, with
/// `last_obs`, the outputs for the observations after the window and the state after the
/// window (zeroed where the episode ended at its last step).
fn window_rollout_outputs(
    net: &LstmNet,
    b: &Batch,
    last_obs: Option<&[f32]>,
    h0: &[f32],
    device: &Device,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let Some(seq) = &b.sequence else {
        return (Vec::new(), Vec::new(), Vec::new());
    };
    let n = seq.num_envs;
    let state = if h0.is_empty() {
        net.zero_state(n, device)
    } else {
        LstmState::from_flat(h0, net.lstm.len(), net.hidden(), device)
    };
    let obs = tensor2(b.obs.clone(), b.obs_dim, device).reshape([seq.steps, n, b.obs_dim]);
    let keep = Tensor::<2>::from_data(TensorData::new(seq.keep.clone(), [seq.steps, n]), device);
    let (all, after) = net.sequence(obs, keep, state);
    let Some(last_obs) = last_obs else {
        return (values(all), Vec::new(), Vec::new());
    };
    let last_keep = Tensor::<2>::from_data(TensorData::new(seq.last_keep.clone(), [1, n]), device);
    let last = tensor2(last_obs.to_vec(), b.obs_dim, device).reshape([1, n, b.obs_dim]);
    let kept = LstmState {
        layers: after
            .layers
            .iter()
            .map(|(h, c)| {
                let k = last_keep.clone().reshape([n, 1]);
                (h.clone() * k.clone(), c.clone() * k)
            })
            .collect(),
    };
    let (last_out, _) = net.sequence(last, last_keep.clone(), after);
    (values(all), values(last_out), kept.to_flat())
}

lstm_ppo_net!(RecurrentActor, actor_h0);

impl PolicyNet for RecurrentActor {
    /// Recurrent `arch` only.
    fn fresh(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let n = usize::from(arch.action_dim);
        Self {
            net: LstmNet::new(arch, n, rng, device),
            log_std: Param::from_tensor(Tensor::from_data(
                TensorData::new(vec![init_std.ln(); n], [n]),
                device,
            )),
        }
    }

    fn with_std_at_most(mut self, max_std: f32) -> Self {
        let ln_max = max_std.ln();
        self.log_std = self
            .log_std
            .map(|t| t.clamp_max(ln_max).detach().require_grad());
        self
    }

    fn log_std(&self) -> Tensor<1> {
        self.log_std.val()
    }

    fn std(&self) -> Vec<f32> {
        values(self.log_std.val().exp())
    }

    fn payload(&self) -> Vec<f32> {
        self.net.payload()
    }

    fn from_payload(
        arch: &Architecture,
        payload: &[f32],
        std: &[f32],
        device: &Device,
    ) -> Option<Self> {
        if std.len() != usize::from(arch.action_dim) {
            return None;
        }
        let log_std: Vec<f32> = std.iter().map(|s| s.ln()).collect();
        Some(Self {
            net: LstmNet::from_payload(arch, payload, device)?,
            log_std: Param::from_tensor(Tensor::from_data(
                TensorData::new(log_std, [std.len()]),
                device,
            )),
        })
    }

    fn with_output_bias(mut self, action: f32) -> Self {
        self.net.head = self.net.head.with_output_bias(action);
        self
    }
}

impl ValueNet for RecurrentCritic {
    /// `arch`'s shape with one output.
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        Self {
            net: LstmNet::new(arch, 1, rng, device),
        }
    }
}

lstm_ppo_net!(RecurrentCritic, critic_h0);
