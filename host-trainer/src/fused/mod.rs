//! The PPO minibatch step of the feed-forward actor and critic (rows A-D) written out by
//! hand on the CPU: the same math as [`crate::ppo`]'s `burn` passes (forward, clipped
//! surrogate with the Gaussian log-likelihood of a log-parameterised σ, entropy bonus,
//! clipped value loss, KL(π_old ‖ π), backward, the global gradient-norm clip and Adam as
//! [`crate::ppo::adam`] configures it), without a graph: parameters, gradients and Adam's
//! moments are flat `f32` vectors, activations live in buffers allocated once, the matrix
//! products are `matrixmultiply`'s `sgemm` (AVX-512/AVX2 FMA kernels chosen at run time).
//!
//! **Layout.** A network's parameters are flat in `burn`'s visiting order: per layer the
//! weight `[in, out]` row-major (`burn`'s `Linear` layout) then the bias, and for the actor
//! log σ last. [`crate::grads::flatten_gradients`] gives `burn`'s gradients in the same
//! order, which is what the parity tests (`host-trainer/tests/fused.rs`) compare.
//!
//! **Chunks.** A minibatch runs in chunks of [`CHUNK`] samples: each chunk's forward pass,
//! loss head and backward pass, the weight gradients accumulated over the chunks. Every
//! per-sample term of the loss depends on that sample only (the means divide by the
//! minibatch size), so this is the minibatch's gradient, with activations that stay in
//! cache.
//!
//! **Threads.** As in the `burn` path, the actor's and the critic's passes run on two
//! threads; the gradients are clipped together by their global norm, then each network
//! takes its Adam step.
//!
//! The `burn` modules stay the networks of record: [`FusedLearner::new`] copies their
//! parameters in, [`FusedLearner::write_to`] copies them back, so checkpoints, export,
//! evaluation and the guard see `burn` modules as before. Adam's moments live in
//! [`FusedOptim`], which the learner keeps between updates and the checkpoint saves.

use crate::batch::{Batch, LN_2PI};
use crate::config::PpoConfig;
use crate::model::{Actor, Critic, values};
use crate::update::{UpdateStats, adapt_learning_rate};
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Tensor, TensorData};
use firmware_core::nn::ACTION_DIM;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;

/// Samples per chunk of a minibatch (see the module doc).
pub const CHUNK: usize = 1024;

/// Adam's β₁ ([`crate::ppo::adam`]: PyTorch's default).
const BETA_1: f32 = 0.9;
/// Adam's β₂.
const BETA_2: f32 = 0.999;
/// Adam's ε.
const EPSILON: f32 = 1e-8;

/// One network's Adam state: first and second moments per parameter (flat, in the
/// network's layout) and the step count of the bias correction.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AdamMoments {
    /// First moments.
    pub moment_1: Vec<f32>,
    /// Second moments.
    pub moment_2: Vec<f32>,
    /// Steps taken.
    pub time: u32,
}

impl AdamMoments {
    /// A fresh state for `n` parameters.
    pub fn new(n: usize) -> Self {
        Self {
            moment_1: vec![0.0; n],
            moment_2: vec![0.0; n],
            time: 0,
        }
    }

    /// One Adam step of `params` along `grads` at learning rate `lr`, in `burn`'s
    /// arithmetic (burn-optim's `AdaptiveMomentum::transform`, then `param − lr·update`).
    pub fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f64) {
        self.time += 1;
        let t = self.time as i32;
        let bias_correction2_sqrt = (1.0 - BETA_2.powi(t)).sqrt();
        let combined = bias_correction2_sqrt / (1.0 - BETA_1.powi(t));
        let eps = EPSILON * bias_correction2_sqrt;
        let (f1, f2) = (1.0 - BETA_1, 1.0 - BETA_2);
        let lr = lr as f32;
        for (((p, &g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(&mut self.moment_1)
            .zip(&mut self.moment_2)
        {
            *m = *m * BETA_1 + g * f1;
            *v = *v * BETA_2 + g * g * f2;
            let update = (*m * combined) / (v.sqrt() + eps);
            *p -= update * lr;
        }
    }
}

/// Adam's state for both networks of the fused update.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FusedOptim {
    /// The actor's.
    pub actor: AdamMoments,
    /// The critic's.
    pub critic: AdamMoments,
}

impl FusedOptim {
    /// As safetensors (the checkpoint's `fused_adam.safetensors`): the four moment vectors
    /// as f32 tensors, the step counts in the metadata.
    pub fn to_safetensors(&self) -> Result<Vec<u8>, String> {
        let bytes = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let parts = [
            ("actor.moment_1", bytes(&self.actor.moment_1)),
            ("actor.moment_2", bytes(&self.actor.moment_2)),
            ("critic.moment_1", bytes(&self.critic.moment_1)),
            ("critic.moment_2", bytes(&self.critic.moment_2)),
        ];
        let views = parts
            .iter()
            .map(|(name, data)| {
                TensorView::new(Dtype::F32, vec![data.len() / 4], data)
                    .map(|v| (name.to_string(), v))
                    .map_err(|e| e.to_string())
            })
            .collect::<Result<Vec<_>, _>>()?;
        let meta = HashMap::from([
            ("actor.time".to_string(), self.actor.time.to_string()),
            ("critic.time".to_string(), self.critic.time.to_string()),
        ]);
        safetensors::tensor::serialize(views, Some(meta)).map_err(|e| e.to_string())
    }

    /// Reads [`FusedOptim::to_safetensors`]'s bytes.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self, String> {
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| e.to_string())?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| e.to_string())?;
        let tensor = |name: &str| -> Result<Vec<f32>, String> {
            let view = st.tensor(name).map_err(|e| format!("{name}: {e}"))?;
            if view.dtype() != Dtype::F32 {
                return Err(format!("{name}: not f32"));
            }
            Ok(view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect())
        };
        let meta = header.metadata().clone().unwrap_or_default();
        let time = |name: &str| -> Result<u32, String> {
            meta.get(name)
                .and_then(|t| t.parse().ok())
                .ok_or_else(|| format!("{name} missing"))
        };
        Ok(Self {
            actor: AdamMoments {
                moment_1: tensor("actor.moment_1")?,
                moment_2: tensor("actor.moment_2")?,
                time: time("actor.time")?,
            },
            critic: AdamMoments {
                moment_1: tensor("critic.moment_1")?,
                moment_2: tensor("critic.moment_2")?,
                time: time("critic.time")?,
            },
        })
    }
}

/// A feed-forward network as flat parameters (see the module doc for the layout).
#[derive(Clone, Debug)]
struct FlatNet {
    /// Layer widths, input first.
    sizes: Vec<usize>,
    /// Parameters.
    params: Vec<f32>,
    /// Per layer: offsets of the weight and of the bias in `params`.
    offsets: Vec<(usize, usize)>,
}

impl FlatNet {
    /// The parameters of `module` (an actor or a critic) whose MLP has layer widths `sizes`.
    fn of<M: Module>(module: &M, sizes: Vec<usize>) -> Self {
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

    fn layers(&self) -> usize {
        self.sizes.len() - 1
    }

    /// Where the MLP's parameters end (log σ follows in the actor).
    fn mlp_len(&self) -> usize {
        let l = self.layers();
        self.offsets[l - 1].1 + self.sizes[l]
    }
}

/// The widths of an MLP's layers, input first.
fn mlp_widths(mlp: &crate::model::Mlp) -> Vec<usize> {
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
struct Collect(Vec<f32>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.0.extend(values(param.val()));
    }
}

/// Overwrites a module's float parameters, in visiting order, from a flat slice (keeping
/// their ids and whether they require gradients).
struct Overwrite<'a> {
    values: &'a [f32],
    at: usize,
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
struct Workspace {
    x: Vec<f32>,
    hidden: Vec<Vec<f32>>,
    y: Vec<f32>,
    d_a: Vec<f32>,
    d_b: Vec<f32>,
}

impl Workspace {
    fn new(sizes: &[usize]) -> Self {
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
struct Side {
    net: FlatNet,
    grad: Vec<f32>,
    adam: AdamMoments,
    ws: Workspace,
}

impl Side {
    fn new(net: FlatNet, adam: Option<AdamMoments>) -> Self {
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
    fn outputs(&mut self, obs: &[f32]) -> Vec<f32> {
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
    fn pass(
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
fn forward(net: &FlatNet, ws: &mut Workspace, m: usize) {
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

/// `c[m, n] = a[m, k] · b[k, n] + beta · c` with `a` and `b` at the given (row, column)
/// strides and `c` row-major.
#[allow(clippy::too_many_arguments)]
fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    (rsa, csa): (usize, usize),
    b: &[f32],
    (rsb, csb): (usize, usize),
    beta: f32,
    c: &mut [f32],
) {
    if m == 0 || n == 0 {
        return;
    }
    let last = |rows: usize, cols: usize, rs: usize, cs: usize| (rows - 1) * rs + (cols - 1) * cs;
    assert!(k == 0 || (last(m, k, rsa, csa) < a.len() && last(k, n, rsb, csb) < b.len()));
    assert!(m * n <= c.len());
    // SAFETY: the asserts keep every element the strides address inside the slices; `c`
    // is exclusively borrowed and does not alias `a` or `b`.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.as_ptr(),
            rsa as isize,
            csa as isize,
            b.as_ptr(),
            rsb as isize,
            csb as isize,
            beta,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

/// `exp(x)` without branches (Cephes' `expf`: range reduction by ln 2, a degree-6
/// polynomial, the power of two built in the exponent bits), so that loops over it
/// vectorise; relative error ~2e-7. Inputs are clamped to [-87, 88].
#[inline(always)]
fn exp_approx(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 · 2²³: adding it rounds to an integer
    let x = x.clamp(-87.0, 88.0);
    let t = x * core::f32::consts::LOG2_E + MAGIC;
    let n = t - MAGIC;
    let ni = (t.to_bits() as i32).wrapping_sub(0x4B40_0000);
    let r = x - n * 0.693_359_4 + n * 2.121_944_4e-4;
    let p = ((((1.987_569_1e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let y = p * r * r + r + 1.0;
    y * f32::from_bits(((ni + 127) << 23) as u32)
}

/// `tanh` over a slice: `1 − 2/(e^{2x} + 1)` (absolute error ~1e-7, the same size as
/// `burn`'s `2σ(2x) − 1` of [`crate::model::fast_tanh`]). The loop is compiled for AVX-512
/// and for AVX2 besides the baseline (SSE2) and the widest the CPU has runs: the same
/// operations in every lane (no FMA contraction), so the same numbers whichever runs. It
/// was a fifth of a minibatch step on SSE2.
fn tanh_in_place(v: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked just above).
            return unsafe { tanh_avx512(v) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { tanh_avx2(v) };
        }
    }
    tanh_loop(v);
}

/// [`tanh_in_place`]'s loop, inlined into each target-feature copy.
#[inline(always)]
fn tanh_loop(v: &mut [f32]) {
    for x in v {
        *x = 1.0 - 2.0 / (exp_approx(2.0 * *x) + 1.0);
    }
}

/// [`tanh_loop`] compiled for AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn tanh_avx512(v: &mut [f32]) {
    tanh_loop(v);
}

/// [`tanh_loop`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn tanh_avx2(v: &mut [f32]) {
    tanh_loop(v);
}

/// `d ← d · (1 − h²)`: the gradient through `h = tanh(z)`.
fn tanh_backward(d: &mut [f32], h: &[f32]) {
    for (d, &h) in d.iter_mut().zip(h) {
        *d *= 1.0 - h * h;
    }
}

/// What the actor's pass measures on a minibatch.
#[derive(Clone, Copy, Debug, Default)]
struct ActorStats {
    surrogate: f64,
    entropy: f64,
    kl: f64,
    clip_fraction: f64,
}

/// The actor's pass: clipped surrogate, entropy bonus, KL before the step; gradients into
/// `side.grad` (log σ's last).
fn actor_pass(side: &mut Side, b: &Batch, idx: &[usize], p: &PpoConfig) -> ActorStats {
    let ls_at = side.net.mlp_len();
    let log_std: [f32; ACTION_DIM] = core::array::from_fn(|k| side.net.params[ls_at + k]);
    let inv_std = log_std.map(|l| (-l).exp());
    let std_now = log_std.map(f32::exp);
    let sum_log_std: f32 = log_std.iter().sum();
    let norm_const = 0.5 * LN_2PI * ACTION_DIM as f32;
    let inv_n = 1.0 / idx.len().max(1) as f32;
    let (lo, hi) = (1.0 - p.clip, 1.0 + p.clip);
    let mut kl = 0.0f64;
    let mut surrogate = 0.0f64;
    let mut clipped_count = 0usize;
    let mut d_log_std = [0.0f64; ACTION_DIM];
    side.pass(b, idx, |rows, mean, d_mean| {
        for ((&i, mu), dmu) in rows
            .iter()
            .zip(mean.chunks_exact(ACTION_DIM))
            .zip(d_mean.chunks_exact_mut(ACTION_DIM))
        {
            let a = &b.actions[i * ACTION_DIM..(i + 1) * ACTION_DIM];
            let om = &b.old_mean[i * ACTION_DIM..(i + 1) * ACTION_DIM];
            let mut z = [0.0f32; ACTION_DIM];
            let mut sq = 0.0f32;
            for k in 0..ACTION_DIM {
                let (s, so) = (f64::from(std_now[k]), f64::from(b.old_std[k]));
                let dm = f64::from(om[k] - mu[k]);
                kl += (s / so).ln() + (so * so + dm * dm) / (2.0 * s * s) - 0.5;
                z[k] = (a[k] - mu[k]) * inv_std[k];
                sq += z[k] * z[k];
            }
            let log_prob = (sq * -0.5 - sum_log_std) - norm_const;
            let ratio = (log_prob - b.old_log_prob[i]).exp();
            let clipped = ratio.clamp(lo, hi);
            if (ratio - 1.0).abs() > p.clip {
                clipped_count += 1;
            }
            let adv = b.advantages[i];
            let (u, v) = (-adv * ratio, -adv * clipped);
            surrogate += f64::from(u.max(v));
            // d loss / d ratio: the unclipped branch's, or the clipped one's, zero outside
            // the clip range.
            let d_ratio = if u >= v { -adv * inv_n } else { 0.0 };
            let d_lp = d_ratio * ratio;
            for k in 0..ACTION_DIM {
                dmu[k] = z[k] * inv_std[k] * d_lp;
                d_log_std[k] += f64::from(d_lp * (z[k] * z[k] - 1.0));
            }
        }
    });
    for (g, d) in side.grad[ls_at..].iter_mut().zip(d_log_std) {
        *g = d as f32 - p.entropy_coef;
    }
    let n = idx.len().max(1) as f64;
    ActorStats {
        surrogate: surrogate / n,
        entropy: f64::from(sum_log_std + 0.5 * (1.0 + LN_2PI) * ACTION_DIM as f32),
        kl: kl / n,
        clip_fraction: clipped_count as f64 / n,
    }
}

/// The critic's pass: the clipped value loss (before its coefficient), gradients of
/// `value_coef ×` it into `side.grad`.
fn critic_pass(side: &mut Side, b: &Batch, idx: &[usize], p: &PpoConfig) -> f64 {
    let scale = p.value_coef / idx.len().max(1) as f32;
    let mut loss = 0.0f64;
    side.pass(b, idx, |rows, v, dv| {
        for ((&i, &v), dv) in rows.iter().zip(v).zip(dv) {
            let (old, ret) = (b.old_values[i], b.returns[i]);
            let delta = v - old;
            let v_clipped = old + delta.clamp(-p.clip, p.clip);
            let (e1, e2) = ((v - ret) * (v - ret), (v_clipped - ret) * (v_clipped - ret));
            loss += f64::from(e1.max(e2));
            *dv = if e1 >= e2 {
                2.0 * (v - ret) * scale
            } else if delta.abs() < p.clip {
                2.0 * (v_clipped - ret) * scale
            } else {
                0.0
            };
        }
    });
    loss / idx.len().max(1) as f64
}

fn squared(v: &[f32]) -> f64 {
    v.iter().map(|&g| f64::from(g) * f64::from(g)).sum()
}

/// The feed-forward actor and critic as the fused update runs them.
#[derive(Clone, Debug)]
pub struct FusedLearner {
    actor: Side,
    critic: Side,
}

impl FusedLearner {
    /// The networks' parameters copied from `actor` and `critic`, Adam's moments from
    /// `optim` (fresh where absent or of another shape).
    pub fn new(actor: &Actor, critic: &Critic, optim: Option<FusedOptim>) -> Self {
        let (oa, oc) = optim.map_or((None, None), |o| (Some(o.actor), Some(o.critic)));
        Self {
            actor: Side::new(FlatNet::of(actor, mlp_widths(&actor.mlp)), oa),
            critic: Side::new(FlatNet::of(critic, mlp_widths(&critic.mlp)), oc),
        }
    }

    /// Copies the parameters back into `actor` and `critic` (ids kept).
    pub fn write_to(&self, actor: &mut Actor, critic: &mut Critic) {
        fn write<'a>(values: &'a [f32]) -> Overwrite<'a> {
            Overwrite { values, at: 0 }
        }
        *actor = actor.clone().map(&mut write(&self.actor.net.params));
        *critic = critic.clone().map(&mut write(&self.critic.net.params));
    }

    /// Adam's state.
    pub fn optim(&self) -> FusedOptim {
        FusedOptim {
            actor: self.actor.adam.clone(),
            critic: self.critic.adam.clone(),
        }
    }

    /// Adam's state, the learner consumed.
    pub fn into_optim(self) -> FusedOptim {
        FusedOptim {
            actor: self.actor.adam,
            critic: self.critic.adam,
        }
    }

    /// The actor's means for every row of `obs`, the critic's values for them and for every
    /// row of `last_obs` (the observations after the window): what PPO's batch needs, the
    /// two networks on two threads.
    pub fn rollout_outputs(
        &mut self,
        obs: &[f32],
        last_obs: &[f32],
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (actor, critic) = (&mut self.actor, &mut self.critic);
        std::thread::scope(|s| {
            let critic_job = s.spawn(|| (critic.outputs(obs), critic.outputs(last_obs)));
            let mean = actor.outputs(obs);
            let (values, last) = critic_job
                .join()
                .unwrap_or_else(|e| std::panic::resume_unwind(e));
            (mean, values, last)
        })
    }

    /// The gradients of the actor's loss (surrogate − entropy bonus) and of the critic's
    /// (`value_coef` × value loss) on the samples `idx` of `b`, flat in `burn`'s order (for
    /// the parity tests; no step is taken).
    pub fn gradients(&mut self, b: &Batch, idx: &[usize], p: &PpoConfig) -> (Vec<f32>, Vec<f32>) {
        actor_pass(&mut self.actor, b, idx, p);
        critic_pass(&mut self.critic, b, idx, p);
        (self.actor.grad.clone(), self.critic.grad.clone())
    }

    /// One PPO minibatch step on the samples `idx` of `b`, as
    /// [`crate::ppo::Learner::train_minibatch`] takes it: both passes (on two threads when
    /// `parallel`), the KL-adapted `learning_rate`, the global gradient clip, both Adam steps;
    /// with `train_actor` off only the critic learns and the rate stays.
    pub fn train_minibatch(
        &mut self,
        b: &Batch,
        idx: &[usize],
        p: &PpoConfig,
        learning_rate: &mut f64,
        train_actor: bool,
        parallel: bool,
    ) -> UpdateStats {
        let skipped = |lr: f64| UpdateStats {
            skipped: 1,
            learning_rate: lr,
            ..UpdateStats::default()
        };
        let max = f64::from(p.max_grad_norm);
        if !train_actor {
            let value_loss = critic_pass(&mut self.critic, b, idx, p);
            let norm = squared(&self.critic.grad).sqrt();
            if !(norm.is_finite() && value_loss.is_finite()) {
                return skipped(*learning_rate);
            }
            if norm > max {
                let factor = (max / (norm + 1e-6)) as f32;
                self.critic.grad.iter_mut().for_each(|g| *g *= factor);
            }
            let critic_lr = p.critic_learning_rate.unwrap_or(*learning_rate);
            let Side {
                net, grad, adam, ..
            } = &mut self.critic;
            adam.step(&mut net.params, grad, critic_lr);
            return UpdateStats {
                value_loss,
                grad_norm: norm,
                learning_rate: *learning_rate,
                ..UpdateStats::default()
            };
        }
        let (actor, critic) = (&mut self.actor, &mut self.critic);
        let (a, value_loss) = if parallel {
            std::thread::scope(|s| {
                let critic_job = s.spawn(|| critic_pass(critic, b, idx, p));
                let a = actor_pass(actor, b, idx, p);
                let c = critic_job
                    .join()
                    .unwrap_or_else(|e| std::panic::resume_unwind(e));
                (a, c)
            })
        } else {
            (actor_pass(actor, b, idx, p), critic_pass(critic, b, idx, p))
        };
        let norm = (squared(&actor.grad) + squared(&critic.grad)).sqrt();
        if !(norm.is_finite()
            && a.surrogate.is_finite()
            && value_loss.is_finite()
            && a.kl.is_finite())
        {
            return skipped(*learning_rate);
        }
        *learning_rate = adapt_learning_rate(*learning_rate, a.kl, p);
        if norm > max {
            let factor = (max / (norm + 1e-6)) as f32;
            actor.grad.iter_mut().for_each(|g| *g *= factor);
            critic.grad.iter_mut().for_each(|g| *g *= factor);
        }
        let lr = *learning_rate;
        actor.adam.step(&mut actor.net.params, &actor.grad, lr);
        if let Some(max_std) = p.max_std {
            let ln_max = max_std.ln();
            let ls_at = actor.net.mlp_len();
            for l in &mut actor.net.params[ls_at..] {
                *l = l.min(ln_max);
            }
        }
        let critic_lr = p.critic_learning_rate.unwrap_or(lr);
        critic
            .adam
            .step(&mut critic.net.params, &critic.grad, critic_lr);
        UpdateStats {
            surrogate_loss: a.surrogate,
            value_loss,
            entropy: a.entropy,
            kl: a.kl,
            clip_fraction: a.clip_fraction,
            grad_norm: norm,
            learning_rate: lr,
            skipped: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_and_tanh_match_std() {
        let mut worst_exp = 0.0f32;
        let mut worst_tanh = 0.0f32;
        for i in -40_000..=40_000 {
            let x = i as f32 * 0.002;
            worst_exp = worst_exp.max(((exp_approx(x) - x.exp()) / x.exp()).abs());
            let mut t = [x];
            tanh_in_place(&mut t);
            worst_tanh = worst_tanh.max((t[0] - x.tanh()).abs());
        }
        assert!(worst_exp < 5e-7, "exp relative error {worst_exp}");
        let xs: Vec<f32> = (-5000..5000).map(|i| i as f32 * 0.0031).collect();
        let mut base = xs.clone();
        tanh_loop(&mut base);
        let mut dispatched = xs;
        tanh_in_place(&mut dispatched);
        assert_eq!(base, dispatched, "the vectorised tanh gives other numbers");
        assert!(worst_tanh < 3e-7, "tanh absolute error {worst_tanh}");
    }

    #[test]
    fn fused_optim_survives_its_safetensors() {
        let m = |n: usize, x: f32| AdamMoments {
            moment_1: (0..n).map(|i| i as f32 * x).collect(),
            moment_2: (0..n).map(|i| i as f32 * x * x).collect(),
            time: n as u32,
        };
        let o = FusedOptim {
            actor: m(7, 0.5),
            critic: m(3, -2.0),
        };
        let back = FusedOptim::from_safetensors(&o.to_safetensors().unwrap()).unwrap();
        assert_eq!(back, o);
    }

    #[test]
    fn gemm_with_transposed_operands_matches_a_plain_loop() {
        let (m, k, n) = (5, 7, 3);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        // a stored as [k, m] (transposed), b as [k, n].
        let at: Vec<f32> = (0..k * m).map(|j| a[(j % m) * k + j / m]).collect();
        let mut c = vec![1.0f32; m * n];
        gemm(m, k, n, &at, (1, m), &b, (n, 1), 1.0, &mut c);
        for i in 0..m {
            for j in 0..n {
                let want: f32 = 1.0 + (0..k).map(|l| a[i * k + l] * b[l * n + j]).sum::<f32>();
                assert!((c[i * n + j] - want).abs() < 1e-5);
            }
        }
    }
}
