//! A feed-forward time-trial policy embedded in a larger network of another Table 1 row, so
//! that the larger network starts as the policy itself (`warm_start.transplant`): a warm
//! start from an RL-trained policy that is exact rather than fitted.
//!
//! The source is an MLP (row A: 17 inputs, hidden layers of 128 and 128, 4 outputs); the
//! target has at least as many inputs, whose first ones are the source's (the layouts are
//! prefixes of one another, docs/DESIGN.md "Observations"), an optional LSTM stack and an MLP
//! head with at least as many hidden layers, each as wide.
//!
//! Where the target has layers the source has not (the LSTM stack before the head, hidden
//! layers after the source's last), they **carry** each value `z` through: [`Carry::UNITS`]
//! units `φ(s z + c_k)` of the layer's nonlinearity, from which the next layer reads
//! `z ≈ Σ_k β_k u_k + β_0` back. The scale `s` and offsets `c_k` are fixed ([`Carry::lstm`],
//! [`Carry::tanh`]; chosen by a search so that every weight stays O(1)); β is the least-squares
//! fit of the identity on [−1, 1] (the pipeline clips every input there; the actions are
//! clamped there). Weights of order one matter: Adam moves every weight by about the
//! learning rate, so a value carried at a small scale ε and read back at 1/ε (the obvious
//! construction, tried first) makes the policy 1/ε times more sensitive to those weights,
//! and PPO's first update at a learning rate of 1e-4 wrecked it (KL 2.9).
//!
//! | target part | what it computes |
//! |---|---|
//! | LSTM layer 0, units `3j + k` for input `j < d` | input and output gates open (bias +B), forget gate shut (−B); cell input `tanh(s x_j + c_k)`: `h = a tanh(a tanh(s x_j + c_k))`, a = σ(B) |
//! | LSTM layer l > 0, the same units | the same of `x̂_j`, read back from layer l − 1's units of input `j` |
//! | MLP layer 0, rows `< w₀` | the source's first layer on the read-back `x̂` (on `x` itself without an LSTM) |
//! | MLP layers 1..m, rows `< wᵢ` | the source's hidden layers as they are |
//! | MLP layer m (when the target has more hidden layers) | units `3r + k` carry the source's output `μ_r = W_out h + b_out` |
//! | MLP layers m+1.. | the same of the read-back `μ̂_r` |
//! | output layer | the read-back `μ̂` (or the source's output layer when there is no extra hidden layer) |
//!
//! A used row reads nothing but the units above that carry the source (zero weights from the
//! others), so the result does not depend on the other units, which keep the target's own
//! fresh initialisation: they start silent in the function and alive for the gradient (their
//! outgoing weights are zero, their incoming ones random). What is lost is the fit's error
//! (4e-6 per LSTM layer, 5e-6 per tanh layer, on values in [−1, 1]) and the forget gate's
//! leak σ(−B) ≈ 6e-6: actions agree to better than 1e-3 (tested in `tests/transplant.rs` against
//! the source flown by firmware-core). The opponent's inputs are read by no used row: the
//! transplant starts blind to the opponent, and PPO has every weight to learn it.

// Rows and columns of payload matrices are addressed by index arithmetic (unit 3j + k of
// input j, and so on); iterators would hide the arithmetic the construction is about.
#![allow(clippy::needless_range_loop)]

use firmware_core::observation::ObservationSpec;
use firmware_core::policy::{Architecture, TensorKind};

/// B: the bias that opens an LSTM gate (σ(B) = 1 − 6e-6) or, negated, shuts it.
pub const GATE_BIAS: f32 = 12.0;

/// How a layer of nonlinearity φ carries a value `z ∈ [−1, 1]`: [`Carry::UNITS`] units
/// `φ(scale · z + offsets[k])`, read back as `Σ_k beta[k] u_k + beta0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Carry {
    /// s: the units' common input weight.
    pub scale: f64,
    /// c_k: the units' biases.
    pub offsets: [f64; Carry::UNITS],
    /// β_k: the read-back weights.
    pub beta: [f64; Carry::UNITS],
    /// β_0: the read-back bias.
    pub beta0: f64,
}

impl Carry {
    /// Units per carried value.
    pub const UNITS: usize = 3;

    /// The LSTM's carry: φ(p) = a tanh(a tanh(p)) (input and output gate a = σ(B), the
    /// forget gate shut), s = 0.15, c = −0.75, 0, 0.75; the fit's error is 3.9e-6 with
    /// β ≤ 4.7.
    pub fn lstm() -> Self {
        let a = f64::from(sigmoid(GATE_BIAS));
        Self::fit(move |p| a * (a * p.tanh()).tanh(), 0.15, [-0.75, 0.0, 0.75])
    }

    /// A tanh layer's carry: s = 0.25, c = −1, 0, 1; the fit's error is 4.5e-6 with β ≤ 2.74.
    pub fn tanh() -> Self {
        Self::fit(f64::tanh, 0.25, [-1.0, 0.0, 1.0])
    }

    /// β by least squares of the identity on 801 points of [−1, 1] (normal equations).
    fn fit(phi: impl Fn(f64) -> f64, scale: f64, offsets: [f64; Self::UNITS]) -> Self {
        const N: usize = Carry::UNITS + 1;
        let mut ata = [[0.0; N]; N];
        let mut atz = [0.0; N];
        for i in 0..=800 {
            let z = -1.0 + f64::from(i) / 400.0;
            let mut f = [1.0; N];
            for (fk, c) in f.iter_mut().zip(offsets) {
                *fk = phi(scale * z + c);
            }
            for r in 0..N {
                atz[r] += f[r] * z;
                for c in 0..N {
                    ata[r][c] += f[r] * f[c];
                }
            }
        }
        let x = solve(ata, atz);
        let mut beta = [0.0; Self::UNITS];
        beta.copy_from_slice(&x[..Self::UNITS]);
        Self {
            scale,
            offsets,
            beta,
            beta0: x[Self::UNITS],
        }
    }

    /// The read-back of the carried value from the units `u` (for tests and checks).
    pub fn read(&self, u: &[f64; Self::UNITS]) -> f64 {
        self.beta.iter().zip(u).map(|(b, u)| b * u).sum::<f64>() + self.beta0
    }
}

/// Gaussian elimination with partial pivoting of a small, well-conditioned system.
fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> [f64; N] {
    for col in 0..N {
        let pivot = (col..N)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap_or(col);
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..N {
            let f = a[row][col] / a[col][col];
            for k in col..N {
                a[row][k] -= f * a[col][k];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let s: f64 = (row + 1..N).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x
}

/// Why a source does not embed in a target.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TransplantError(pub String);

impl core::fmt::Display for TransplantError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for TransplantError {}

/// The target's payload with the source embedded in it: `source` (payload order of
/// `source_arch`, a feed-forward network) inside `target_init` (a payload of `target_arch`,
/// normally its fresh initialisation, which the units the source does not use keep).
pub fn transplant(
    source_arch: &Architecture,
    source: &[f32],
    target_arch: &Architecture,
    target_init: &[f32],
) -> Result<Vec<f32>, TransplantError> {
    check(source_arch, target_arch)?;
    if source.len() != source_arch.param_count() {
        return Err(TransplantError(format!(
            "the source has {} weights, its architecture {}",
            source.len(),
            source_arch.param_count()
        )));
    }
    if target_init.len() != target_arch.param_count() {
        return Err(TransplantError(format!(
            "the target has {} weights, its architecture {}",
            target_init.len(),
            target_arch.param_count()
        )));
    }
    let mut out = target_init.to_vec();
    let shape = Shape::new(source_arch, target_arch);
    let dst = Tensors::new(target_arch);
    // The LSTM stack carries the source's inputs on units 3j + k.
    for layer in 0..usize::from(target_arch.lstm_layers) {
        carry_inputs(&dst, &mut out, &shape, layer);
    }
    embed_source(&Tensors::new(source_arch), source, &dst, &mut out, &shape);
    carry_outputs(&dst, &mut out, &shape);
    Ok(out)
}

/// The sizes the construction works with.
struct Shape {
    /// The source's observation size: the values the LSTM stack carries.
    d: usize,
    /// The target's observation size.
    target_obs: usize,
    /// LSTM units per layer (0 without an LSTM).
    h: usize,
    /// True when the target has an LSTM stack.
    lstm: bool,
    /// Hidden widths of the source's MLP and of the target's head.
    src_hidden: Vec<usize>,
    dst_hidden: Vec<usize>,
    /// Action values.
    actions: usize,
}

impl Shape {
    fn new(source: &Architecture, target: &Architecture) -> Self {
        let widths = |a: &Architecture| a.mlp_hidden.iter().map(|&w| usize::from(w)).collect();
        Self {
            d: usize::from(source.obs_dim),
            target_obs: usize::from(target.obs_dim),
            h: usize::from(target.lstm_hidden),
            lstm: target.lstm_layers > 0,
            src_hidden: widths(source),
            dst_hidden: widths(target),
            actions: usize::from(source.action_dim),
        }
    }

    /// Inputs of the target's head layer `i`.
    fn dst_input(&self, i: usize) -> usize {
        match i {
            0 if self.lstm => self.h,
            0 => self.target_obs,
            _ => self.dst_hidden[i - 1],
        }
    }

    /// Inputs of the source's layer `i`.
    fn src_input(&self, i: usize) -> usize {
        if i == 0 {
            self.d
        } else {
            self.src_hidden[i - 1]
        }
    }
}

/// LSTM layer `layer` carries the source's `d` inputs (layer 0: the observation's first `d`
/// values; above: read back from the layer below's carrying units) on units `3j + k`, gates
/// open, forget gate shut.
fn carry_inputs(dst: &Tensors, out: &mut [f32], shape: &Shape, layer: usize) {
    const K: usize = Carry::UNITS;
    let (d, h) = (shape.d, shape.h);
    let lstm = Carry::lstm();
    let f = |v: f64| v as f32;
    let input = if layer == 0 { shape.target_obs } else { h };
    let w_ih = dst.get_mut(out, TensorKind::LstmWeightIh(layer));
    for gate in 0..4 {
        for u in 0..d * K {
            row_mut(w_ih, input, gate * h + u).fill(0.0);
        }
    }
    for j in 0..d {
        for k in 0..K {
            let row = row_mut(w_ih, input, 2 * h + j * K + k);
            if layer == 0 {
                row[j] = f(lstm.scale);
            } else {
                for m in 0..K {
                    row[j * K + m] = f(lstm.scale * lstm.beta[m]);
                }
            }
        }
    }
    let w_hh = dst.get_mut(out, TensorKind::LstmWeightHh(layer));
    for gate in 0..4 {
        for u in 0..d * K {
            row_mut(w_hh, h, gate * h + u).fill(0.0);
        }
    }
    let bias = dst.get_mut(out, TensorKind::LstmBias(layer));
    let read_bias = if layer == 0 {
        0.0
    } else {
        lstm.scale * lstm.beta0
    };
    for j in 0..d {
        for (k, c) in lstm.offsets.iter().enumerate() {
            let u = j * K + k;
            bias[u] = GATE_BIAS; // input gate
            bias[h + u] = -GATE_BIAS; // forget gate
            bias[2 * h + u] = f(read_bias + c); // cell input
            bias[3 * h + u] = GATE_BIAS; // output gate
        }
    }
}

/// The source's layers in the head's first layers; its output either in the target's output
/// layer or, when the head is deeper, on `K` carrying units per action value.
fn embed_source(src: &Tensors, source: &[f32], dst: &Tensors, out: &mut [f32], shape: &Shape) {
    const K: usize = Carry::UNITS;
    let (lstm, tanh) = (Carry::lstm(), Carry::tanh());
    let f = |v: f64| v as f32;
    let (m, n) = (shape.src_hidden.len(), shape.dst_hidden.len());
    let actions = shape.actions;
    for i in 0..=m {
        let (sw, sb) = (
            src.get(source, TensorKind::LinearWeight(i)),
            src.get(source, TensorKind::LinearBias(i)),
        );
        let carried = i == m && n > m;
        let rows = if i < m { shape.src_hidden[i] } else { actions };
        let cols = shape.dst_input(i);
        // Each source row becomes one target row, or K carrying rows for the output.
        let mut targets = Vec::new();
        for r in 0..rows {
            let row_in = row_of(sw, shape.src_input(i), r);
            let reads_carry = i == 0 && shape.lstm;
            let mut weights = vec![0.0f64; cols];
            let mut b = f64::from(sb[r]);
            for (j, &w) in row_in.iter().enumerate() {
                if reads_carry {
                    for k in 0..K {
                        weights[j * K + k] = f64::from(w) * lstm.beta[k];
                    }
                    b += f64::from(w) * lstm.beta0;
                } else {
                    weights[j] = f64::from(w);
                }
            }
            if carried {
                for (k, c) in tanh.offsets.iter().enumerate() {
                    let w: Vec<f64> = weights.iter().map(|w| w * tanh.scale).collect();
                    targets.push((r * K + k, w, tanh.scale * b + c));
                }
            } else {
                targets.push((r, weights, b));
            }
        }
        let w = dst.get_mut(out, TensorKind::LinearWeight(i));
        for (r, weights, _) in &targets {
            for (o, v) in row_mut(w, cols, *r).iter_mut().zip(weights) {
                *o = f(*v);
            }
        }
        let b = dst.get_mut(out, TensorKind::LinearBias(i));
        for (r, _, bias) in &targets {
            b[*r] = f(*bias);
        }
    }
}

/// The carried outputs through the head's remaining hidden layers, read back at the output.
fn carry_outputs(dst: &Tensors, out: &mut [f32], shape: &Shape) {
    const K: usize = Carry::UNITS;
    let tanh = Carry::tanh();
    let f = |v: f64| v as f32;
    let (m, n) = (shape.src_hidden.len(), shape.dst_hidden.len());
    let actions = shape.actions;
    for i in (m + 1..=n).filter(|_| n > m) {
        let cols = shape.dst_hidden[i - 1];
        let w = dst.get_mut(out, TensorKind::LinearWeight(i));
        let mut biases = Vec::new();
        for r in 0..actions {
            let read = |k: usize| r * K + k;
            if i == n {
                let row = row_mut(w, cols, r);
                row.fill(0.0);
                for k in 0..K {
                    row[read(k)] = f(tanh.beta[k]);
                }
                biases.push((r, tanh.beta0));
            } else {
                for (k, c) in tanh.offsets.iter().enumerate() {
                    let row = row_mut(w, cols, r * K + k);
                    row.fill(0.0);
                    for m in 0..K {
                        row[read(m)] = f(tanh.scale * tanh.beta[m]);
                    }
                    biases.push((r * K + k, tanh.scale * tanh.beta0 + c));
                }
            }
        }
        let b = dst.get_mut(out, TensorKind::LinearBias(i));
        for (r, v) in biases {
            b[r] = f(v);
        }
    }
}

/// Refuses a pair the construction does not cover, naming the first misfit.
fn check(source: &Architecture, target: &Architecture) -> Result<(), TransplantError> {
    let refuse = |why: String| Err(TransplantError(why));
    if source.lstm_layers > 0 {
        return refuse("the source must be feed-forward (an MLP)".into());
    }
    if source.action_dim != target.action_dim {
        return refuse(format!(
            "the source has {} actions, the target {}",
            source.action_dim, target.action_dim
        ));
    }
    if source.obs_dim > target.obs_dim {
        return refuse(format!(
            "the source observes {} values, more than the target's {}",
            source.obs_dim, target.obs_dim
        ));
    }
    let units = |values: u16| values * Carry::UNITS as u16;
    if target.lstm_layers > 0 && target.lstm_hidden < units(source.obs_dim) {
        return refuse(format!(
            "the target's LSTM ({} units) cannot carry the source's {} inputs ({} units each)",
            target.lstm_hidden,
            source.obs_dim,
            Carry::UNITS
        ));
    }
    let (s, t) = (&source.mlp_hidden, &target.mlp_hidden);
    if t.len() < s.len() {
        return refuse(format!(
            "the target's head has {} hidden layers, fewer than the source's {}",
            t.len(),
            s.len()
        ));
    }
    for (i, (sw, tw)) in s.iter().zip(t.iter()).enumerate() {
        if tw < sw {
            return refuse(format!(
                "the target's hidden layer {i} has {tw} units, fewer than the source's {sw}"
            ));
        }
    }
    if let Some(w) = t
        .iter()
        .skip(s.len())
        .find(|&&w| w < u16::from(source.action_dim))
    {
        return refuse(format!(
            "a target hidden layer of {w} units cannot carry {} actions",
            source.action_dim
        ));
    }
    Ok(())
}

/// Refuses a target spec whose shared terms differ from the source's: the source's inputs
/// must be the first values of the target's, on the same scales and fold.
pub fn spec_fits(
    source: &ObservationSpec,
    target: &ObservationSpec,
) -> Result<(), TransplantError> {
    let shared = |s: &ObservationSpec| {
        (
            s.version,
            s.gate_position_scale_m,
            s.velocity_scale_mps,
            s.body_rate_scale_radps,
            s.clip,
        )
    };
    if source.layout.dim() > target.layout.dim() {
        return Err(TransplantError(format!(
            "the source observes {} values, more than the run's {}",
            source.layout.dim(),
            target.layout.dim()
        )));
    }
    if shared(source) != shared(target) {
        return Err(TransplantError(format!(
            "its observation spec (version, gate, velocity and rate scales, clip) {:?} differs from the run's {:?} (env.velocity_scale_mps, env.fold_mirror?)",
            shared(source),
            shared(target)
        )));
    }
    Ok(())
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Where each tensor of an architecture lies in its payload.
struct Tensors(Vec<(TensorKind, usize, usize)>);

impl Tensors {
    fn new(arch: &Architecture) -> Self {
        let mut at = 0;
        let mut out = Vec::new();
        for t in arch.tensors() {
            let len = t.rows * t.cols.max(1);
            out.push((t.kind, at, len));
            at += len;
        }
        Self(out)
    }

    fn span(&self, kind: TensorKind) -> (usize, usize) {
        self.0
            .iter()
            .find(|(k, _, _)| *k == kind)
            .map(|&(_, at, len)| (at, len))
            .expect("a tensor of the checked architecture")
    }

    fn get<'p>(&self, payload: &'p [f32], kind: TensorKind) -> &'p [f32] {
        let (at, len) = self.span(kind);
        &payload[at..at + len]
    }

    fn get_mut<'p>(&self, payload: &'p mut [f32], kind: TensorKind) -> &'p mut [f32] {
        let (at, len) = self.span(kind);
        &mut payload[at..at + len]
    }
}

fn row_of(matrix: &[f32], cols: usize, r: usize) -> &[f32] {
    &matrix[r * cols..(r + 1) * cols]
}

fn row_mut(matrix: &mut [f32], cols: usize, r: usize) -> &mut [f32] {
    &mut matrix[r * cols..(r + 1) * cols]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each carry reads its value back to the fit's stated error over [−1, 1], with
    /// read-back weights of order one (the point of carrying rather than scaling by ε).
    #[test]
    fn a_carried_value_reads_back_with_weights_of_order_one() {
        let a = f64::from(sigmoid(GATE_BIAS));
        let lstm = |p: f64| a * (a * p.tanh()).tanh();
        for (carry, phi, bound) in [
            (Carry::lstm(), &lstm as &dyn Fn(f64) -> f64, 5e-6),
            (Carry::tanh(), &f64::tanh as &dyn Fn(f64) -> f64, 5e-6),
        ] {
            let worst = (0..=2000)
                .map(|i| -1.0 + f64::from(i) / 1000.0)
                .map(|z| {
                    let u = carry.offsets.map(|c| phi(carry.scale * z + c));
                    (carry.read(&u) - z).abs()
                })
                .fold(0.0, f64::max);
            assert!(worst < bound, "{carry:?}: {worst}");
            assert!(carry.beta.iter().all(|b| b.abs() < 5.0), "{carry:?}");
        }
    }
}
