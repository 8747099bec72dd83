//! The feed-forward actor and critic of rows A-D on `burn`: separate MLPs of the same shape
//! (docs/DESIGN.md "Learning"), tanh hidden activations, a linear output, and a learned state-independent
//! log standard deviation for the Gaussian policy.
//!
//! The actor's weights map one-to-one onto a firmware-core blob payload ([`Actor::payload`],
//! [`Actor::from_payload`]): `burn` keeps a linear layer's weight as `[in, out]`, the blob as
//! PyTorch's `[out, in]`, so the export transposes.
//!
//! **tanh.** `burn`'s flex backend evaluates `tanh` with a scalar call per element; the
//! identity `tanh(x) = 2·σ(2x) − 1` runs on its vectorised sigmoid and made the update 1.6×
//! faster (docs/burn-0.22.md). The two differ by at most 1.2e-7, far inside the 1e-5 parity
//! bound with firmware-core (which uses libm's `tanhf`), tested in
//! `host-trainer/tests/parity.rs`.

use crate::batch::{Batch, Minibatch, gather, tensor2};
use crate::nets::{PolicyNet, PpoNet, ValueNet};
use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::policy::{Architecture, TensorKind};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// `tanh(x)` as `2·σ(2x) − 1` (see the module doc).
pub fn fast_tanh<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    sigmoid(x.mul_scalar(2.0)).mul_scalar(2.0).sub_scalar(1.0)
}

/// A multilayer perceptron: tanh after every layer but the last.
#[derive(Module, Debug)]
pub struct Mlp {
    /// The linear layers, input first.
    pub layers: Vec<Linear>,
}

impl Mlp {
    /// Layers of widths `sizes[0] → sizes[1] → …`, initialised as PyTorch's `nn.Linear`
    /// (weights and biases uniform in ±1/√fan_in) from `rng`, so a seed fixes the network
    /// whatever backend runs it.
    pub fn new(sizes: &[usize], rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let layers = sizes
            .windows(2)
            .map(|w| {
                let (fan_in, fan_out) = (w[0], w[1]);
                let bound = 1.0 / (fan_in as f32).sqrt();
                let mut draw = |n: usize| -> Vec<f32> {
                    (0..n).map(|_| rng.random_range(-bound..bound)).collect()
                };
                // Drawn in PyTorch's [out, in] order, stored transposed.
                let w_out_in = draw(fan_in * fan_out);
                let bias = draw(fan_out);
                linear_from_pytorch(&w_out_in, &bias, fan_in, fan_out, device)
            })
            .collect();
        Self { layers }
    }

    /// The same network with every output's bias set to `value`.
    pub fn with_output_bias(mut self, value: f32) -> Self {
        if let Some(last) = self.layers.last_mut() {
            let n = last.weight.val().dims()[1];
            let device = last.weight.val().device();
            let b = Tensor::<1>::from_data(TensorData::new(vec![value; n], [n]), &device);
            last.bias = Some(Param::from_tensor(b));
        }
        self
    }

    /// Forward pass over a batch `[n, in]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len().saturating_sub(1);
        let mut x = x;
        for (i, layer) in self.layers.iter().enumerate() {
            x = layer.forward(x);
            if i < last {
                x = fast_tanh(x);
            }
        }
        x
    }
}

/// A `burn` linear layer from a PyTorch-layout weight `[out, in]` (row-major) and bias.
pub(crate) fn linear_from_pytorch(
    w_out_in: &[f32],
    bias: &[f32],
    fan_in: usize,
    fan_out: usize,
    device: &Device,
) -> Linear {
    let w = Tensor::<2>::from_data(
        TensorData::new(w_out_in.to_vec(), [fan_out, fan_in]),
        device,
    )
    .transpose();
    let b = Tensor::<1>::from_data(TensorData::new(bias.to_vec(), [fan_out]), device);
    Linear {
        weight: Param::from_tensor(w),
        bias: Some(Param::from_tensor(b)),
    }
}

/// Values of a tensor as `f32`, row-major. `convert` makes the data f32, so the copy out
/// cannot meet a dtype mismatch; any other representation is read element by element
/// rather than lost.
pub fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    let data = t.into_data().convert::<f32>();
    match data.try_to_vec::<f32>() {
        Ok(v) => v,
        Err(_) => data.iter::<f32>().collect(),
    }
}

/// The Gaussian policy: an MLP giving the mean and a learned log-std per action.
#[derive(Module, Debug)]
pub struct Actor {
    /// Mean network.
    pub mlp: Mlp,
    /// log σ per action dimension (state-independent).
    pub log_std: Param<Tensor<1>>,
}

/// The value function: an MLP with one output.
#[derive(Module, Debug)]
pub struct Critic {
    /// Value network.
    pub mlp: Mlp,
}

/// The layer widths of a feed-forward Table 1 architecture, input to output.
pub fn mlp_sizes(arch: &Architecture) -> Vec<usize> {
    core::iter::once(usize::from(arch.obs_dim))
        .chain(arch.mlp_hidden.iter().map(|&w| usize::from(w)))
        .chain(core::iter::once(usize::from(arch.action_dim)))
        .collect()
}

impl Actor {
    /// The Gaussian mean for a batch of observations `[n, obs]`.
    pub fn mean(&self, obs: Tensor<2>) -> Tensor<2> {
        self.mlp.forward(obs)
    }
}

/// [`PpoNet`] for a feed-forward network with its MLP in field `mlp`: no state, so
/// minibatches are samples.
macro_rules! mlp_ppo_net {
    ($net:ty) => {
        impl PpoNet for $net {
            const RECURRENT: bool = false;
            fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
                mlp_outputs(&self.mlp, &b.obs, b.obs_dim, mb, device)
            }
            fn rollout_outputs(
                &self,
                b: &Batch,
                last: Option<&[f32]>,
                device: &Device,
            ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
                mlp_rollout_outputs(&self.mlp, &b.obs, last, b.obs_dim, device)
            }
        }
    };
}

/// `mlp`'s outputs for `mb`'s samples, whose inputs are `rows` (`dim` values per sample).
fn mlp_outputs(mlp: &Mlp, rows: &[f32], dim: usize, mb: &Minibatch, device: &Device) -> Tensor<2> {
    mlp.forward(tensor2(gather(rows, dim, &mb.samples), dim, device))
}

/// `mlp`'s outputs for every row of `rows` (`dim` values each) and, with `last`, for the
/// inputs after the window (no state to carry).
fn mlp_rollout_outputs(
    mlp: &Mlp,
    rows: &[f32],
    last: Option<&[f32]>,
    dim: usize,
    device: &Device,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let all = values(mlp.forward(tensor2(rows.to_vec(), dim, device)));
    let last = last.map_or_else(Vec::new, |l| {
        values(mlp.forward(tensor2(l.to_vec(), dim, device)))
    });
    (all, last, Vec::new())
}

mlp_ppo_net!(Actor);

impl PolicyNet for Actor {
    /// Feed-forward `arch` only.
    fn fresh(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let sizes = mlp_sizes(arch);
        let mlp = Mlp::new(&sizes, rng, device);
        let n = usize::from(arch.action_dim);
        let log_std = Tensor::<1>::from_data(TensorData::new(vec![init_std.ln(); n], [n]), device);
        Self {
            mlp,
            log_std: Param::from_tensor(log_std),
        }
    }

    fn log_std(&self) -> Tensor<1> {
        self.log_std.val()
    }

    fn std(&self) -> Vec<f32> {
        values(self.log_std.val().exp())
    }

    /// Per layer the weight `[out, in]` row-major, then the bias.
    fn payload(&self) -> Vec<f32> {
        let mut out = Vec::new();
        for layer in &self.mlp.layers {
            out.extend(values(layer.weight.val().transpose()));
            if let Some(b) = &layer.bias {
                out.extend(values(b.val()));
            }
        }
        out
    }

    /// `None` also when `arch` is recurrent.
    fn from_payload(
        arch: &Architecture,
        payload: &[f32],
        std: &[f32],
        device: &Device,
    ) -> Option<Self> {
        if arch.is_recurrent()
            || payload.len() != arch.param_count()
            || std.len() != usize::from(arch.action_dim)
        {
            return None;
        }
        let mut layers = Vec::new();
        let mut offset = 0;
        let tensors = arch.tensors();
        for pair in tensors.chunks(2) {
            let [w, b] = pair else { return None };
            if !matches!(w.kind, TensorKind::LinearWeight(_)) {
                return None;
            }
            let wv = payload.get(offset..offset + w.len())?;
            offset += w.len();
            let bv = payload.get(offset..offset + b.len())?;
            offset += b.len();
            layers.push(linear_from_pytorch(wv, bv, w.cols, w.rows, device));
        }
        let n = std.len();
        let log_std: Vec<f32> = std.iter().map(|s| s.ln()).collect();
        Some(Self {
            mlp: Mlp { layers },
            log_std: Param::from_tensor(Tensor::from_data(TensorData::new(log_std, [n]), device)),
        })
    }

    fn with_output_bias(mut self, action: f32) -> Self {
        self.mlp = self.mlp.with_output_bias(action);
        self
    }

    fn with_std_at_most(mut self, max_std: f32) -> Self {
        let ln_max = max_std.ln();
        self.log_std = self
            .log_std
            .map(|t| t.clamp_max(ln_max).detach().require_grad());
        self
    }
}

impl Critic {
    /// V(obs) for a batch `[n, obs]`, as `[n, 1]`.
    pub fn value(&self, obs: Tensor<2>) -> Tensor<2> {
        self.mlp.forward(obs)
    }
}

impl ValueNet for Critic {
    /// The hidden widths of `arch` and one output.
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let mut sizes = mlp_sizes(arch);
        if let Some(last) = sizes.last_mut() {
            *last = 1;
        }
        Self {
            mlp: Mlp::new(&sizes, rng, device),
        }
    }
}

mlp_ppo_net!(Critic);

/// A value function on the env's privileged state (`[ppo] critic = "privileged-mlp"`): an
/// MLP with the row's head widths and one output, whose input is the batch's
/// [`crate::batch::CriticInputs`] (the noise-free observation, the episode's randomised
/// airframe and latency, its time left: `sitl::env::VecEnv::privileged_observations`). It
/// carries no state, so beside a recurrent actor its minibatches are the actor's windows and
/// it reads their samples one by one. It is never deployed.
#[derive(Module, Debug)]
pub struct PrivilegedCritic {
    /// Value network.
    pub mlp: Mlp,
}

impl PrivilegedCritic {
    /// The critic's input width for `arch`: its observation and the privileged extras.
    pub fn input_dim(arch: &Architecture) -> usize {
        usize::from(arch.obs_dim) + sitl::env::PRIVILEGED_EXTRA
    }
}

impl PpoNet for PrivilegedCritic {
    const RECURRENT: bool = false;

    /// Zeros when the batch holds no privileged state (a rollout that did not record it).
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
        let Some(c) = &b.critic else {
            return Tensor::zeros([mb.samples.len(), 1], device);
        };
        mlp_outputs(&self.mlp, &c.obs, c.dim, mb, device)
    }

    fn rollout_outputs(
        &self,
        b: &Batch,
        last: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let Some(c) = &b.critic else {
            return (vec![0.0; b.len()], Vec::new(), Vec::new());
        };
        let last = last.map(|_| &c.last_obs[..]);
        mlp_rollout_outputs(&self.mlp, &c.obs, last, c.dim, device)
    }
}

impl ValueNet for PrivilegedCritic {
    /// The head widths of `arch` (its MLP layers: the whole network of a feed-forward row)
    /// on [`PrivilegedCritic::input_dim`], one output.
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let mut sizes = mlp_sizes(arch);
        if let [first, .., last] = sizes.as_mut_slice() {
            (*first, *last) = (Self::input_dim(arch), 1);
        }
        Self {
            mlp: Mlp::new(&sizes, rng, device),
        }
    }
}
