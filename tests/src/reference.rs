//! An independent float64 reference of the policies and the observation pipeline.
//!
//! Written from the papers' and PyTorch's definitions, not from firmware-core's code: it walks
//! the flat weight list with its own layout rules (PyTorch `nn.LSTM` / `nn.Linear` parameter
//! order, LSTM biases summed), uses rotation matrices where firmware-core uses quaternion
//! algebra, and computes in f64 with std's `tanh` and `exp`.

/// The shape of a policy: observation size, LSTM layers and width, MLP hidden widths.
#[derive(Clone, Debug)]
pub struct Shape {
    /// Observation size.
    pub obs_dim: usize,
    /// LSTM layers (0 for none).
    pub lstm_layers: usize,
    /// LSTM hidden size.
    pub hidden: usize,
    /// MLP hidden widths.
    pub mlp: Vec<usize>,
}

/// A float64 policy with its LSTM state.
#[derive(Clone, Debug)]
pub struct ReferencePolicy {
    shape: Shape,
    weights: Vec<f64>,
    h: Vec<Vec<f64>>,
    c: Vec<Vec<f64>>,
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// `W x + b` with `W` the next `out × in` values (row-major) and `b` the next `out`.
fn affine(w: &[f64], at: &mut usize, x: &[f64], out: usize) -> Vec<f64> {
    let n = x.len();
    let weight = &w[*at..*at + out * n];
    let bias = &w[*at + out * n..*at + out * n + out];
    *at += out * n + out;
    (0..out)
        .map(|r| bias[r] + (0..n).map(|k| weight[r * n + k] * x[k]).sum::<f64>())
        .collect()
}

impl ReferencePolicy {
    /// A policy of `shape` with `weights` (payload order).
    pub fn new(shape: Shape, weights: &[f32]) -> Self {
        let layers = shape.lstm_layers;
        let hidden = shape.hidden;
        Self {
            shape,
            weights: weights.iter().map(|&w| f64::from(w)).collect(),
            h: vec![vec![0.0; hidden]; layers],
            c: vec![vec![0.0; hidden]; layers],
        }
    }

    /// One step: the Gaussian mean for `obs`.
    pub fn step(&mut self, obs: &[f32]) -> Vec<f64> {
        assert_eq!(obs.len(), self.shape.obs_dim);
        let w = &self.weights;
        let mut at = 0;
        let mut x: Vec<f64> = obs.iter().map(|&v| f64::from(v)).collect();
        let hs = self.shape.hidden;
        for l in 0..self.shape.lstm_layers {
            // PyTorch: weight_ih_l{l} [4H, in], weight_hh_l{l} [4H, H], bias [4H] (summed).
            let n = x.len();
            let w_ih = &w[at..at + 4 * hs * n];
            at += 4 * hs * n;
            let w_hh = &w[at..at + 4 * hs * hs];
            at += 4 * hs * hs;
            let b = &w[at..at + 4 * hs];
            at += 4 * hs;
            let h_prev = self.h[l].clone();
            let z: Vec<f64> = (0..4 * hs)
                .map(|r| {
                    b[r] + (0..n).map(|k| w_ih[r * n + k] * x[k]).sum::<f64>()
                        + (0..hs).map(|k| w_hh[r * hs + k] * h_prev[k]).sum::<f64>()
                })
                .collect();
            for j in 0..hs {
                let (i, f, g, o) = (
                    sigmoid(z[j]),
                    sigmoid(z[hs + j]),
                    z[2 * hs + j].tanh(),
                    sigmoid(z[3 * hs + j]),
                );
                self.c[l][j] = f * self.c[l][j] + i * g;
                self.h[l][j] = o * self.c[l][j].tanh();
            }
            x = self.h[l].clone();
        }
        for &width in &self.shape.mlp {
            x = affine(w, &mut at, &x, width)
                .into_iter()
                .map(f64::tanh)
                .collect();
        }
        let y = affine(w, &mut at, &x, 4);
        assert_eq!(
            at,
            w.len(),
            "reference consumed {at} of {} weights",
            w.len()
        );
        y
    }
}

/// A vehicle state in f64: position (m), attitude (w, x, y, z), world velocity (m/s), body
/// rates (rad/s).
#[derive(Clone, Copy, Debug)]
pub struct State64 {
    /// Position (m).
    pub p: [f64; 3],
    /// Attitude quaternion (w, x, y, z), body → world.
    pub q: [f64; 4],
    /// Velocity (m/s, world).
    pub v: [f64; 3],
    /// Body rates (rad/s).
    pub w: [f64; 3],
}

/// The rotation matrix of a unit quaternion (w, x, y, z).
pub fn rotation(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// `R v`.
pub fn mat_vec(r: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| r[i][0] * v[0] + r[i][1] * v[1] + r[i][2] * v[2])
}

/// `Rᵀ v`.
pub fn mat_t_vec(r: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| r[0][i] * v[0] + r[1][i] * v[1] + r[2][i] * v[2])
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scaled_clip(v: [f64; 3], scale: f64) -> [f64; 3] {
    v.map(|x| (x / scale).clamp(-1.0, 1.0))
}

/// The paper's observation (17, 20 or 30 values) from the formulas of docs/DESIGN.md
/// "Observations", in f64.
pub fn observation(
    dim: usize,
    own: &State64,
    gate_center: [f64; 3],
    gate_q: [f64; 4],
    previous_action: [f64; 4],
    opponent: Option<&State64>,
) -> Vec<f64> {
    let pi = std::f64::consts::PI;
    let r_gate = rotation(gate_q);
    let r_body = rotation(own.q);
    let mut o = Vec::with_capacity(dim);
    o.extend(scaled_clip(
        mat_t_vec(&r_gate, sub(gate_center, own.p)),
        12.0,
    ));
    o.extend(own.q);
    o.extend(scaled_clip(mat_t_vec(&r_body, own.v), 3.0));
    o.extend(scaled_clip(own.w, pi));
    o.extend(previous_action);
    if dim > 17 {
        let opp = opponent.expect("opponent needed");
        o.extend(scaled_clip(mat_t_vec(&r_body, sub(opp.p, own.p)), 12.0));
        if dim > 20 {
            o.extend(opp.q);
            o.extend(scaled_clip(mat_t_vec(&r_body, opp.v), 3.0));
            let w_world = mat_vec(&rotation(opp.q), opp.w);
            o.extend(scaled_clip(mat_t_vec(&r_body, w_world), pi));
        }
    }
    assert_eq!(o.len(), dim);
    o
}
