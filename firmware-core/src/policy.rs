//! The policy architectures of the paper's Table 1 (rows A–G) and their runtime dispatch.
//!
//! | row | observation | LSTM | MLP head (tanh) | parameters |
//! |---|---|---|---|---|
//! | A | 17 | — | 128, 128 | 19,332 |
//! | B | 20 | — | 128, 128 | 19,716 |
//! | C, D | 30 | — | 256, 128, 128, 64 | 65,860 |
//! | E | 30 | 1 × 128 | 256, 128, 128, 64 | 172,356 |
//! | F | 30 | 2 × 128 | 256, 128, 128 | 295,940 |
//! | G | 30 | 2 × 128 | 256, 128, 128, 64 | 303,940 |
//!
//! (Counts with the LSTM's two PyTorch biases stored as one; PyTorch counts 1,024 more for
//! F and G, 512 for E.) D differs from C only in its training reward.

use crate::format::{BlobError, WeightDtype};
use crate::nn::{
    ACTION_DIM, LANES, Lanes, LstmPolicy, LstmStackLanes, LstmStackState, Mlp2, Mlp3, Mlp4,
    MlpPolicy, WeightReader,
};
use crate::observation::{Observation, ObservationLayout};
use serde::{Deserialize, Serialize};

/// Most hidden layers an MLP head may have in a blob header.
pub const MAX_MLP_LAYERS: usize = 6;

/// Hidden-layer activation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Activation {
    /// Hyperbolic tangent (the paper's choice).
    Tanh,
}

/// A row of the paper's Table 1.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum TableRow {
    /// Single-agent MLP 2 × 128, 17 inputs (stage 1).
    A,
    /// MLP 2 × 128, 20 inputs.
    B,
    /// MLP 256, 128, 128, 64, 30 inputs.
    C,
    /// As C, trained with the sparse competition reward.
    D,
    /// 1-layer LSTM 128 + MLP 256, 128, 128, 64.
    E,
    /// 2-layer LSTM 128 + MLP 256, 128, 128.
    F,
    /// 2-layer LSTM 128 + MLP 256, 128, 128, 64 (the paper's method).
    G,
}

impl TableRow {
    /// All rows, in order.
    pub const ALL: [Self; 7] = [
        Self::A,
        Self::B,
        Self::C,
        Self::D,
        Self::E,
        Self::F,
        Self::G,
    ];

    /// The row's letter.
    pub const fn letter(self) -> char {
        match self {
            Self::A => 'A',
            Self::B => 'B',
            Self::C => 'C',
            Self::D => 'D',
            Self::E => 'E',
            Self::F => 'F',
            Self::G => 'G',
        }
    }

    /// The row whose letter is `letter` (either case): the one table from a letter to a
    /// row, and so to its [`Architecture::table1`], that the trainer, its command line and
    /// the tools share. `None` outside A-G.
    pub fn from_letter(letter: char) -> Option<Self> {
        let letter = letter.to_ascii_uppercase();
        Self::ALL.into_iter().find(|r| r.letter() == letter)
    }

    /// What the row's policy observes (paper): the 17 time-trial values (A), plus the
    /// opponent's relative position (B), or the full opponent state (C-G).
    pub const fn observation_layout(self) -> ObservationLayout {
        match self {
            Self::A => ObservationLayout::TimeTrial17,
            Self::B => ObservationLayout::OpponentPosition20,
            _ => ObservationLayout::FullOpponent30,
        }
    }
}

/// The shape of a policy network, as a blob header records it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Architecture {
    /// Observation size (17, 20 or 30).
    pub obs_dim: u16,
    /// Number of stacked LSTM layers (0 for a feed-forward policy).
    pub lstm_layers: u8,
    /// LSTM hidden size (0 when there is no LSTM).
    pub lstm_hidden: u16,
    /// Widths of the MLP head's hidden layers, input side first.
    pub mlp_hidden: heapless::Vec<u16, MAX_MLP_LAYERS>,
    /// Number of actions (4: one per motor).
    pub action_dim: u8,
    /// Hidden activation.
    pub activation: Activation,
}

impl Architecture {
    /// The architecture of a Table 1 row.
    pub fn table1(row: TableRow) -> Self {
        let (obs_dim, lstm_layers, widths): (u16, u8, &[u16]) = match row {
            TableRow::A => (17, 0, &[128, 128]),
            TableRow::B => (20, 0, &[128, 128]),
            TableRow::C | TableRow::D => (30, 0, &[256, 128, 128, 64]),
            TableRow::E => (30, 1, &[256, 128, 128, 64]),
            TableRow::F => (30, 2, &[256, 128, 128]),
            TableRow::G => (30, 2, &[256, 128, 128, 64]),
        };
        let mut mlp_hidden = heapless::Vec::new();
        for &w in widths {
            // At most four widths, within the capacity of six.
            let _ = mlp_hidden.push(w);
        }
        Self {
            obs_dim,
            lstm_layers,
            lstm_hidden: if lstm_layers > 0 { 128 } else { 0 },
            mlp_hidden,
            action_dim: ACTION_DIM as u8,
            activation: Activation::Tanh,
        }
    }

    /// True when the policy carries a recurrent state.
    pub fn is_recurrent(&self) -> bool {
        self.lstm_layers > 0
    }

    /// Number of parameters in the payload, in payload order (see [`crate::nn`]).
    pub fn param_count(&self) -> usize {
        let h = usize::from(self.lstm_hidden);
        let mut n = 0;
        let mut input = usize::from(self.obs_dim);
        for _ in 0..self.lstm_layers {
            n += 4 * h * input + 4 * h * h + 4 * h;
            input = h;
        }
        for &w in &self.mlp_hidden {
            let w = usize::from(w);
            n += input * w + w;
            input = w;
        }
        let out = usize::from(self.action_dim);
        n + input * out + out
    }

    /// Payload bytes of these weights stored as `dtype` (see [`crate::blob`]).
    pub fn payload_bytes(&self, dtype: WeightDtype) -> usize {
        match dtype {
            WeightDtype::F32 => 4 * self.param_count(),
            WeightDtype::I8 => self
                .tensors()
                .iter()
                .map(|t| {
                    if t.cols == 0 {
                        4 * t.rows
                    } else {
                        4 * t.rows + t.rows * crate::nn::i8_row_bytes(t.cols)
                    }
                })
                .sum(),
        }
    }

    /// The shape of every parameter tensor in payload order (host-trainer's `rslrl` module
    /// maps them to RSL-RL's names, `memory_a.rnn.weight_ih_l0`, `actor.0.weight`, …). A bias
    /// entry has 0 columns. The LSTM bias is the sum `bias_ih + bias_hh`.
    pub fn tensors(&self) -> heapless::Vec<TensorShape, 32> {
        let mut out = heapless::Vec::new();
        let h = usize::from(self.lstm_hidden);
        let mut input = usize::from(self.obs_dim);
        for layer in 0..self.lstm_layers {
            let l = usize::from(layer);
            let _ = out.push(TensorShape {
                kind: TensorKind::LstmWeightIh(l),
                rows: 4 * h,
                cols: input,
            });
            let _ = out.push(TensorShape {
                kind: TensorKind::LstmWeightHh(l),
                rows: 4 * h,
                cols: h,
            });
            let _ = out.push(TensorShape {
                kind: TensorKind::LstmBias(l),
                rows: 4 * h,
                cols: 0,
            });
            input = h;
        }
        let widths = self.mlp_hidden.iter().map(|&w| usize::from(w));
        for (i, w) in widths
            .chain(core::iter::once(usize::from(self.action_dim)))
            .enumerate()
        {
            let _ = out.push(TensorShape {
                kind: TensorKind::LinearWeight(i),
                rows: w,
                cols: input,
            });
            let _ = out.push(TensorShape {
                kind: TensorKind::LinearBias(i),
                rows: w,
                cols: 0,
            });
            input = w;
        }
        out
    }
}

/// Which parameter tensor of a policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TensorKind {
    /// `weight_ih` of LSTM layer n, `[4H][in]`.
    LstmWeightIh(usize),
    /// `weight_hh` of LSTM layer n, `[4H][H]`.
    LstmWeightHh(usize),
    /// `bias_ih + bias_hh` of LSTM layer n, `[4H]`.
    LstmBias(usize),
    /// Weight of MLP linear layer n (the last one is the output), `[out][in]`.
    LinearWeight(usize),
    /// Bias of MLP linear layer n, `[out]`.
    LinearBias(usize),
}

/// The shape of one parameter tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TensorShape {
    /// Which tensor.
    pub kind: TensorKind,
    /// Rows (output size).
    pub rows: usize,
    /// Columns (input size); 0 for a bias vector.
    pub cols: usize,
}

impl TensorShape {
    /// Number of values.
    pub fn len(&self) -> usize {
        if self.cols == 0 {
            self.rows
        } else {
            self.rows * self.cols
        }
    }

    /// True when the tensor holds no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Row A: MLP 2 × 128 on 17 inputs.
pub type PolicyA<'w> = MlpPolicy<Mlp2<'w, 17, 128, 128>>;
/// Row B: MLP 2 × 128 on 20 inputs.
pub type PolicyB<'w> = MlpPolicy<Mlp2<'w, 20, 128, 128>>;
/// Rows C and D: MLP 256, 128, 128, 64 on 30 inputs.
pub type PolicyC<'w> = MlpPolicy<Mlp4<'w, 30, 256, 128, 128, 64>>;
/// Row E: 1-layer LSTM 128 + MLP 256, 128, 128, 64.
pub type PolicyE<'w> = LstmPolicy<'w, 30, 128, 0, Mlp4<'w, 128, 256, 128, 128, 64>>;
/// Row F: 2-layer LSTM 128 + MLP 256, 128, 128.
pub type PolicyF<'w> = LstmPolicy<'w, 30, 128, 1, Mlp3<'w, 128, 256, 128, 128>>;
/// Row G: 2-layer LSTM 128 + MLP 256, 128, 128, 64.
pub type PolicyG<'w> = LstmPolicy<'w, 30, 128, 1, Mlp4<'w, 128, 256, 128, 128, 64>>;

/// The recurrent state of a 1-layer LSTM policy (row E).
pub type Lstm1State = LstmStackState<128, 0>;
/// The recurrent state of a 2-layer LSTM policy (rows F, G).
pub type Lstm2State = LstmStackState<128, 1>;

/// A policy network viewing a blob's weights, one variant per supported architecture.
#[derive(Clone, Copy, Debug)]
pub enum Policy<'w> {
    /// Row A.
    A(PolicyA<'w>),
    /// Row B.
    B(PolicyB<'w>),
    /// Rows C, D.
    C(PolicyC<'w>),
    /// Row E.
    E(PolicyE<'w>),
    /// Row F.
    F(PolicyF<'w>),
    /// Row G.
    G(PolicyG<'w>),
}

/// The recurrent state of a [`Policy`], owned by its controller. Held inline (no heap): the
/// size is the largest variant's, which the RAM budget below accounts for.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PolicyState {
    /// A feed-forward policy keeps nothing between steps.
    Stateless,
    /// One LSTM layer.
    Lstm1(Lstm1State),
    /// Two LSTM layers.
    Lstm2(Lstm2State),
}

/// Bytes of a row-G policy's recurrent state plus the activations of one step (the whole
/// controller's budget is `controller::CONTROLLER_G_RAM_BYTES`).
pub const POLICY_G_MEMORY_BYTES: usize =
    core::mem::size_of::<PolicyState>() + PolicyG::SCRATCH_BYTES;

impl PolicyState {
    /// Number of values in [`Self::write_flat`]'s order: per layer, h then c.
    pub fn flat_len(&self) -> usize {
        2 * 128 * self.layers().len()
    }

    /// The state's values, per layer h then c (a simulator's snapshot of a controller).
    /// `false`, writing nothing, unless `out` holds exactly [`Self::flat_len`] values.
    pub fn write_flat(&self, out: &mut [f32]) -> bool {
        if out.len() != self.flat_len() {
            return false;
        }
        for (layer, chunk) in self.layers().iter().zip(out.chunks_exact_mut(256)) {
            let (h, c) = chunk.split_at_mut(128);
            h.copy_from_slice(&layer.h);
            c.copy_from_slice(&layer.c);
        }
        true
    }

    /// Restores the values [`Self::write_flat`] wrote, into a state of the same shape.
    /// `false`, changing nothing, when `values` has another length.
    pub fn read_flat(&mut self, values: &[f32]) -> bool {
        if values.len() != self.flat_len() {
            return false;
        }
        for (layer, chunk) in self.layers_mut().into_iter().zip(values.chunks_exact(256)) {
            let (h, c) = chunk.split_at(128);
            layer.h.copy_from_slice(h);
            layer.c.copy_from_slice(c);
        }
        true
    }

    fn layers(&self) -> heapless::Vec<&crate::nn::LstmLayerState<128>, 2> {
        let mut out = heapless::Vec::new();
        match self {
            Self::Stateless => {}
            Self::Lstm1(s) => {
                let _ = out.push(&s.first);
            }
            Self::Lstm2(s) => {
                let _ = out.push(&s.first);
                for d in &s.deep {
                    let _ = out.push(d);
                }
            }
        }
        out
    }

    fn layers_mut(&mut self) -> heapless::Vec<&mut crate::nn::LstmLayerState<128>, 2> {
        let mut out = heapless::Vec::new();
        match self {
            Self::Stateless => {}
            Self::Lstm1(s) => {
                let _ = out.push(&mut s.first);
            }
            Self::Lstm2(s) => {
                let _ = out.push(&mut s.first);
                for d in &mut s.deep {
                    let _ = out.push(d);
                }
            }
        }
        out
    }

    /// Zeroes the recurrent state in place (no temporary copy on the stack).
    pub fn clear(&mut self) {
        let layers: &mut [crate::nn::LstmLayerState<128>] = match self {
            Self::Stateless => &mut [],
            Self::Lstm1(s) => core::slice::from_mut(&mut s.first),
            Self::Lstm2(s) => {
                s.first.h.fill(0.0);
                s.first.c.fill(0.0);
                &mut s.deep
            }
        };
        for layer in layers {
            layer.h.fill(0.0);
            layer.c.fill(0.0);
        }
    }
}

impl<'w> Policy<'w> {
    /// Views f32 `payload` as the weights of `arch`; the architecture must be one of
    /// Table 1's.
    pub fn from_payload(arch: &Architecture, payload: &'w [f32]) -> Result<Self, BlobError> {
        Self::from_reader(arch, WeightReader::new(payload))
    }

    /// Views the payload behind `r` (either dtype) as the weights of `arch`.
    pub fn from_reader(arch: &Architecture, mut r: WeightReader<'w>) -> Result<Self, BlobError> {
        let matches = |row| *arch == Architecture::table1(row);
        let policy = if matches(TableRow::A) {
            Self::A(MlpPolicy::load(&mut r)?)
        } else if matches(TableRow::B) {
            Self::B(MlpPolicy::load(&mut r)?)
        } else if matches(TableRow::C) {
            Self::C(MlpPolicy::load(&mut r)?)
        } else if matches(TableRow::E) {
            Self::E(LstmPolicy::load(&mut r)?)
        } else if matches(TableRow::F) {
            Self::F(LstmPolicy::load(&mut r)?)
        } else if matches(TableRow::G) {
            Self::G(LstmPolicy::load(&mut r)?)
        } else {
            return Err(BlobError::UnsupportedArchitecture);
        };
        r.finish()?;
        Ok(policy)
    }

    /// Observation size.
    pub fn obs_dim(&self) -> usize {
        match self {
            Self::A(_) => 17,
            Self::B(_) => 20,
            Self::C(_) | Self::E(_) | Self::F(_) | Self::G(_) => 30,
        }
    }

    /// A zeroed recurrent state for this policy.
    pub fn initial_state(&self) -> PolicyState {
        match self {
            Self::A(_) | Self::B(_) | Self::C(_) => PolicyState::Stateless,
            Self::E(_) => PolicyState::Lstm1(Lstm1State::default()),
            Self::F(_) | Self::G(_) => PolicyState::Lstm2(Lstm2State::default()),
        }
    }

    /// True when the policy carries a recurrent state.
    pub fn is_recurrent(&self) -> bool {
        matches!(self, Self::E(_) | Self::F(_) | Self::G(_))
    }

    /// [`Self::act`] of a feed-forward policy (rows A-D) on [`LANES`] observations side by
    /// side (the host's batched rollouts): `obs` holds `LANES` observations of
    /// [`Self::obs_dim`] values one after the other, and lane `l` of the result is bit for
    /// bit `act` of observation `l` (a NaN may be another NaN: which operand's NaN an
    /// operation keeps is the instruction's choice). `None` for a recurrent policy (see
    /// [`Self::step_lanes`]) or another length.
    #[inline(always)]
    pub fn act_lanes(&self, obs: &[f32]) -> Option<[[f32; ACTION_DIM]; LANES]> {
        let y = match self {
            Self::A(p) => p.forward_lanes(&to_lanes::<17>(obs)?),
            Self::B(p) => p.forward_lanes(&to_lanes::<20>(obs)?),
            Self::C(p) => p.forward_lanes(&to_lanes::<30>(obs)?),
            Self::E(_) | Self::F(_) | Self::G(_) => return None,
        };
        from_lanes(&y)
    }

    /// [`Self::act`] of any policy on [`LANES`] observations side by side, advancing each
    /// lane's recurrent state `states[l]` as `act` would: lane `l` is bit for bit `act` of
    /// observation `l` from state `l` (NaNs as in [`Self::act_lanes`]). `None`, with every
    /// state untouched, when `obs` has another length or a state is not this policy's.
    #[inline(always)]
    pub fn step_lanes(
        &self,
        obs: &[f32],
        states: [&mut PolicyState; LANES],
    ) -> Option<[[f32; ACTION_DIM]; LANES]> {
        match self {
            Self::A(_) | Self::B(_) | Self::C(_) => self.act_lanes(obs),
            Self::E(p) => {
                let x = to_lanes::<30>(obs)?;
                let (mut views, mut lanes) = gather_lanes(states, PolicyState::lstm1)?;
                let y = p.step_lanes(&x, &mut lanes);
                scatter_lanes(&lanes, &mut views, &y)
            }
            Self::F(p) => {
                let x = to_lanes::<30>(obs)?;
                let (mut views, mut lanes) = gather_lanes(states, PolicyState::lstm2)?;
                let y = p.step_lanes(&x, &mut lanes);
                scatter_lanes(&lanes, &mut views, &y)
            }
            Self::G(p) => {
                let x = to_lanes::<30>(obs)?;
                let (mut views, mut lanes) = gather_lanes(states, PolicyState::lstm2)?;
                let y = p.step_lanes(&x, &mut lanes);
                scatter_lanes(&lanes, &mut views, &y)
            }
        }
    }

    /// One forward step: the Gaussian mean (unclipped) for `obs`, advancing `state`.
    /// `None` when `obs` or `state` does not belong to this policy.
    pub fn act(&self, obs: &Observation, state: &mut PolicyState) -> Option<[f32; ACTION_DIM]> {
        match (self, state) {
            (Self::A(p), _) => Some(p.forward(obs.as_array::<17>()?)),
            (Self::B(p), _) => Some(p.forward(obs.as_array::<20>()?)),
            (Self::C(p), _) => Some(p.forward(obs.as_array::<30>()?)),
            (Self::E(p), PolicyState::Lstm1(s)) => Some(p.step(obs.as_array::<30>()?, s)),
            (Self::F(p), PolicyState::Lstm2(s)) => Some(p.step(obs.as_array::<30>()?, s)),
            (Self::G(p), PolicyState::Lstm2(s)) => Some(p.step(obs.as_array::<30>()?, s)),
            _ => None,
        }
    }
}

/// `LANES` observations of `N` values, one after the other, as lanes (`None` for another
/// length).
#[inline(always)]
fn to_lanes<const N: usize>(obs: &[f32]) -> Option<Lanes<N>> {
    if obs.len() != N * LANES {
        return None;
    }
    let mut x = [[0.0f32; LANES]; N];
    for (l, o) in obs.chunks_exact(N).enumerate() {
        for (xk, v) in x.iter_mut().zip(o) {
            *xk.get_mut(l)? = *v;
        }
    }
    Some(x)
}

/// Lanes of actions as one action per lane.
#[inline(always)]
fn from_lanes(y: &Lanes<ACTION_DIM>) -> Option<[[f32; ACTION_DIM]; LANES]> {
    let mut means = [[0.0f32; ACTION_DIM]; LANES];
    for (k, yk) in y.iter().enumerate() {
        for (m, v) in means.iter_mut().zip(yk) {
            *m.get_mut(k)? = *v;
        }
    }
    Some(means)
}

/// The LSTM states of `states` (each viewed by `view`; `None`, nothing touched, when one
/// is another policy's) and their values as lanes. (Written without closures: a closure is
/// its own function, which the caller's `#[target_feature]` would not reach.)
#[inline(always)]
#[allow(clippy::type_complexity)]
fn gather_lanes<const DEEP: usize>(
    states: [&mut PolicyState; LANES],
    view: fn(&mut PolicyState) -> Option<&mut LstmStackState<128, DEEP>>,
) -> Option<(
    [Option<&mut LstmStackState<128, DEEP>>; LANES],
    LstmStackLanes<128, DEEP>,
)> {
    let mut views = [const { None }; LANES];
    for (v, s) in views.iter_mut().zip(states) {
        *v = Some(view(s)?);
    }
    let mut lanes = LstmStackLanes::default();
    for (l, v) in views.iter().enumerate() {
        lanes.set_lane(l, v.as_deref()?);
    }
    Some((views, lanes))
}

/// Writes the stepped `lanes` back into `views` and returns the actions `y`, one per lane.
#[inline(always)]
fn scatter_lanes<const DEEP: usize>(
    lanes: &LstmStackLanes<128, DEEP>,
    views: &mut [Option<&mut LstmStackState<128, DEEP>>; LANES],
    y: &Lanes<ACTION_DIM>,
) -> Option<[[f32; ACTION_DIM]; LANES]> {
    for (l, v) in views.iter_mut().enumerate() {
        lanes.get_lane(l, v.as_deref_mut()?);
    }
    from_lanes(y)
}

impl PolicyState {
    fn lstm1(&mut self) -> Option<&mut Lstm1State> {
        match self {
            Self::Lstm1(s) => Some(s),
            _ => None,
        }
    }

    fn lstm2(&mut self) -> Option<&mut Lstm2State> {
        match self {
            Self::Lstm2(s) => Some(s),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one letter table: every row's letter leads back to it in either case, a letter
    /// outside A-G to none, and a row observes as many values as its architecture takes.
    #[test]
    fn row_letters_and_layouts_agree_with_the_architectures() {
        for row in TableRow::ALL {
            assert_eq!(TableRow::from_letter(row.letter()), Some(row));
            assert_eq!(
                TableRow::from_letter(row.letter().to_ascii_lowercase()),
                Some(row)
            );
            assert_eq!(
                row.observation_layout().dim(),
                usize::from(Architecture::table1(row).obs_dim)
            );
        }
        for c in ['H', 'z', '1', ' '] {
            assert_eq!(TableRow::from_letter(c), None);
        }
    }
}
