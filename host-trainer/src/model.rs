//! The stage-1 actor and critic on `burn`: separate MLPs of the same shape (SPEC
//! "Learning"), tanh hidden activations, a linear output, and a learned state-independent
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

use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::policy::{Architecture, TensorKind};
use rand::{Rng, SeedableRng};
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

/// Values of a tensor as `f32`, row-major.
pub fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap_or_default()
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
    /// A fresh actor of `arch` (feed-forward only) with σ = `init_std`.
    pub fn new(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let sizes = mlp_sizes(arch);
        let mlp = Mlp::new(&sizes, rng, device);
        let n = usize::from(arch.action_dim);
        let log_std = Tensor::<1>::from_data(TensorData::new(vec![init_std.ln(); n], [n]), device);
        Self {
            mlp,
            log_std: Param::from_tensor(log_std),
        }
    }

    /// The same actor with its output bias set to `action` on every motor: the mean action
    /// of an all-zero hidden layer (e.g. the hover action, so that the first rollouts hover
    /// instead of falling).
    pub fn with_output_bias(mut self, action: f32) -> Self {
        self.mlp = self.mlp.with_output_bias(action);
        self
    }

    /// The Gaussian mean for a batch of observations `[n, obs]`.
    pub fn mean(&self, obs: Tensor<2>) -> Tensor<2> {
        self.mlp.forward(obs)
    }

    /// σ per action.
    pub fn std(&self) -> Vec<f32> {
        values(self.log_std.val().exp())
    }

    /// The weights in firmware-core payload order (see `Architecture::tensors`): per layer
    /// the weight `[out, in]` row-major, then the bias.
    pub fn payload(&self) -> Vec<f32> {
        let mut out = Vec::new();
        for layer in &self.mlp.layers {
            out.extend(values(layer.weight.val().transpose()));
            if let Some(b) = &layer.bias {
                out.extend(values(b.val()));
            }
        }
        out
    }

    /// An actor holding `payload` (firmware-core order) for `arch`, with σ = `std`.
    /// `None` when the payload does not have `arch`'s parameter count or `arch` is recurrent.
    pub fn from_payload(
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
}

impl Critic {
    /// A fresh critic with the hidden widths of `arch` and one output.
    pub fn new(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let mut sizes = mlp_sizes(arch);
        if let Some(last) = sizes.last_mut() {
            *last = 1;
        }
        Self {
            mlp: Mlp::new(&sizes, rng, device),
        }
    }

    /// V(obs) for a batch `[n, obs]`, as `[n, 1]`.
    pub fn value(&self, obs: Tensor<2>) -> Tensor<2> {
        self.mlp.forward(obs)
    }
}

/// The generator of the network initialisation for `seed` (its own stream, apart from the
/// environment's and the action noise's).
pub fn init_rng(seed: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(u64::MAX);
    rng
}
