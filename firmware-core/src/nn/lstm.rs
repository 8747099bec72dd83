//! The LSTM layers, their stack and the recurrent policy (an LSTM stack, then an MLP head).

use super::kernels::{Matrix, dot, sigmoid, tanh};
use super::lanes::{add_lanes, dot_lanes, expf_lanes, tanh_lanes};
use super::mlp::Head;
use super::{ACTION_DIM, I8_SCRATCH_BYTES, LANES, Lanes, WeightReader};
use crate::format::BlobError;

/// The hidden and cell state of one LSTM layer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LstmLayerState<const H: usize> {
    /// Hidden state h.
    pub h: [f32; H],
    /// Cell state c.
    pub c: [f32; H],
}

impl<const H: usize> Default for LstmLayerState<H> {
    fn default() -> Self {
        Self {
            h: [0.0; H],
            c: [0.0; H],
        }
    }
}

/// The states of one LSTM layer in [`LANES`] envs side by side (`h[k][lane]`): the
/// host's batched inference ([`LstmCell::step_lanes`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LstmLayerLanes<const H: usize> {
    /// Hidden states.
    pub h: Lanes<H>,
    /// Cell states.
    pub c: Lanes<H>,
}

impl<const H: usize> Default for LstmLayerLanes<H> {
    fn default() -> Self {
        Self {
            h: [[0.0; LANES]; H],
            c: [[0.0; LANES]; H],
        }
    }
}

impl<const H: usize> LstmLayerLanes<H> {
    /// Lane `l` set to `s`.
    fn set_lane(&mut self, l: usize, s: &LstmLayerState<H>) {
        for ((h, c), (sh, sc)) in self.h.iter_mut().zip(&mut self.c).zip(s.h.iter().zip(&s.c)) {
            if let (Some(h), Some(c)) = (h.get_mut(l), c.get_mut(l)) {
                (*h, *c) = (*sh, *sc);
            }
        }
    }

    /// Lane `l` written into `s`.
    fn get_lane(&self, l: usize, s: &mut LstmLayerState<H>) {
        for ((sh, sc), (h, c)) in s.h.iter_mut().zip(&mut s.c).zip(self.h.iter().zip(&self.c)) {
            if let (Some(h), Some(c)) = (h.get(l), c.get(l)) {
                (*sh, *sc) = (*h, *c);
            }
        }
    }
}

/// One LSTM layer (PyTorch semantics, gate order i, f, g, o; see the module docs).
#[derive(Clone, Copy, Debug)]
pub struct LstmCell<'w, const IN: usize, const H: usize> {
    weight_ih: Matrix<'w>,
    weight_hh: Matrix<'w>,
    bias: &'w [f32],
}

impl<'w, const IN: usize, const H: usize> LstmCell<'w, IN, H> {
    /// Number of parameters (with the two PyTorch biases stored as one).
    pub const PARAMS: usize = 4 * H * IN + 4 * H * H + 4 * H;

    /// Takes `weight_ih`, `weight_hh`, then the summed bias from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        let weight_ih = r.take_matrix(4 * H, IN)?;
        let weight_hh = r.take_matrix(4 * H, H)?;
        let bias = r.take(4 * H)?;
        Ok(Self {
            weight_ih,
            weight_hh,
            bias,
        })
    }

    /// Advances `state` by one input `x`.
    ///
    /// Gate-major: the pre-activations of all four gates, `(W_ih x + W_hh h) + bias`, row
    /// by row over both weight matrices (f32), or as two matrix-vector products (int8),
    /// then the cell updates. On the host the gate-major form is 59 µs per G controller step against
    /// 84 µs for a unit-by-unit loop that needs only H values of scratch (same session); the
    /// 4H-value buffer (2 KB at H = 128) fits the RAM budget. Kept out of line so its
    /// scratch and the MLP head's never share a stack frame.
    #[inline(never)]
    pub fn step(&self, x: &[f32; IN], state: &mut LstmLayerState<H>) {
        // Pre-activations of the four gates, i f g o.
        let mut z = [[0.0f32; H]; 4];
        let flat = z.as_flattened_mut();
        match (self.weight_ih, self.weight_hh) {
            // f32: both weight streams in one pass per row. Two passes cost the host G step
            // 7 % (68.1 against 63.7 µs, mean of three paired runs); this form is at parity
            // with the code before int8 (61.8 against 63.5 µs, two paired runs).
            (Matrix::F32(w_ih), Matrix::F32(w_hh)) => {
                let rows = w_ih
                    .chunks_exact(IN)
                    .zip(w_hh.chunks_exact(H))
                    .zip(self.bias);
                for (zo, ((ri, rh), bo)) in flat.iter_mut().zip(rows) {
                    *zo = dot(ri, x) + dot(rh, &state.h) + bo;
                }
            }
            (w_ih, w_hh) => {
                w_ih.mul_add(x, flat);
                w_hh.mul_add(&state.h, flat);
                for (zo, b) in flat.iter_mut().zip(self.bias) {
                    *zo += b;
                }
            }
        }
        let [zi, zf, zg, zo] = &z;
        let units = state.h.iter_mut().zip(state.c.iter_mut());
        for ((((h, c), i), f), (g, o)) in units.zip(zi).zip(zf).zip(zg.iter().zip(zo)) {
            let cn = sigmoid(*f) * *c + sigmoid(*i) * tanh(*g);
            *c = cn;
            *h = sigmoid(*o) * tanh(cn);
        }
    }

    /// [`Self::step`] of [`LANES`] inputs and states side by side, each lane the same bits
    /// (f32: the same dot products, sums and libm `expf` per lane; int8 quantises each
    /// input with its own scale, so it runs lane by lane).
    #[inline(always)]
    pub fn step_lanes(&self, x: &Lanes<IN>, state: &mut LstmLayerLanes<H>) {
        let (Matrix::F32(w_ih), Matrix::F32(w_hh)) = (self.weight_ih, self.weight_hh) else {
            let mut one = LstmLayerState::default();
            for l in 0..LANES {
                state.get_lane(l, &mut one);
                self.step(&super::lanes::lane(x, l), &mut one);
                state.set_lane(l, &one);
            }
            return;
        };
        // Pre-activations of the four gates, i f g o: `step`'s `(W_ih x + W_hh h) + bias`.
        // Two passes over the rows, each as `Linear::forward_lanes` writes one (in a single
        // pass the compiler vectorised across rows, with gathers, at a fifth of the speed).
        let mut z = [[[0.0f32; LANES]; H]; 4];
        for (zo, ri) in z.as_flattened_mut().iter_mut().zip(w_ih.chunks_exact(IN)) {
            *zo = dot_lanes(ri, x);
        }
        let rows = w_hh.chunks_exact(H).zip(self.bias);
        for (zo, (rh, bo)) in z.as_flattened_mut().iter_mut().zip(rows) {
            let s = add_lanes(zo, &dot_lanes(rh, &state.h));
            for (zl, sl) in zo.iter_mut().zip(s) {
                *zl = sl + bo;
            }
        }
        let [zi, zf, zg, zo] = &mut z;
        sigmoid_lanes(zi);
        sigmoid_lanes(zf);
        tanh_lanes(zg);
        sigmoid_lanes(zo);
        // c' = σ(f) c + σ(i) tanh(g), then h' = σ(o) tanh(c'), as `step` orders them. One
        // loop over the flattened `H × LANES` values: nested loops were vectorised across
        // the units, with gathers.
        let cells = state.c.as_flattened_mut().iter_mut().zip(zf.as_flattened());
        for ((cl, fl), (il, gl)) in cells.zip(zi.as_flattened().iter().zip(zg.as_flattened())) {
            *cl = *fl * *cl + *il * *gl;
        }
        let mut tc = state.c;
        tanh_lanes(&mut tc);
        let outs = state.h.as_flattened_mut().iter_mut().zip(zo.as_flattened());
        for ((hl, ol), tl) in outs.zip(tc.as_flattened()) {
            *hl = *ol * *tl;
        }
    }
}

/// [`sigmoid`] of every value, [`LANES`] at a time: `1 / (1 + expf(−x))` through
/// [`expf_lanes`], the same bits.
#[inline(always)]
fn sigmoid_lanes(v: &mut [[f32; LANES]]) {
    for x in v.iter_mut() {
        let e = expf_lanes(&x.map(|xl| -xl));
        for (xl, el) in x.iter_mut().zip(e) {
            *xl = 1.0 / (1.0 + el);
        }
    }
}

/// A stack of `1 + DEEP` LSTM layers of width `H` on `IN` inputs.
#[derive(Clone, Copy, Debug)]
pub struct LstmStack<'w, const IN: usize, const H: usize, const DEEP: usize> {
    first: LstmCell<'w, IN, H>,
    deep: [LstmCell<'w, H, H>; DEEP],
}

/// The state of an [`LstmStack`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LstmStackState<const H: usize, const DEEP: usize> {
    /// State of the first layer.
    pub first: LstmLayerState<H>,
    /// States of the layers after it.
    pub deep: [LstmLayerState<H>; DEEP],
}

impl<const H: usize, const DEEP: usize> Default for LstmStackState<H, DEEP> {
    fn default() -> Self {
        Self {
            first: LstmLayerState::default(),
            deep: [LstmLayerState::default(); DEEP],
        }
    }
}

impl<const H: usize, const DEEP: usize> LstmStackState<H, DEEP> {
    /// The top layer's hidden state: the stack's output.
    pub fn output(&self) -> &[f32; H] {
        match self.deep.last() {
            Some(top) => &top.h,
            None => &self.first.h,
        }
    }
}

/// The states of an [`LstmStack`] in [`LANES`] envs side by side.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LstmStackLanes<const H: usize, const DEEP: usize> {
    /// States of the first layer.
    pub first: LstmLayerLanes<H>,
    /// States of the layers after it.
    pub deep: [LstmLayerLanes<H>; DEEP],
}

impl<const H: usize, const DEEP: usize> Default for LstmStackLanes<H, DEEP> {
    fn default() -> Self {
        Self {
            first: LstmLayerLanes::default(),
            deep: [LstmLayerLanes::default(); DEEP],
        }
    }
}

impl<const H: usize, const DEEP: usize> LstmStackLanes<H, DEEP> {
    /// Lane `l` set to `s`.
    pub fn set_lane(&mut self, l: usize, s: &LstmStackState<H, DEEP>) {
        self.first.set_lane(l, &s.first);
        for (d, sd) in self.deep.iter_mut().zip(&s.deep) {
            d.set_lane(l, sd);
        }
    }

    /// Lane `l` written into `s`.
    pub fn get_lane(&self, l: usize, s: &mut LstmStackState<H, DEEP>) {
        self.first.get_lane(l, &mut s.first);
        for (d, sd) in self.deep.iter().zip(&mut s.deep) {
            d.get_lane(l, sd);
        }
    }

    /// The top layer's hidden states: the stack's outputs.
    pub fn output(&self) -> &Lanes<H> {
        match self.deep.last() {
            Some(top) => &top.h,
            None => &self.first.h,
        }
    }
}

impl<'w, const IN: usize, const H: usize, const DEEP: usize> LstmStack<'w, IN, H, DEEP> {
    /// Number of parameters.
    pub const PARAMS: usize = LstmCell::<IN, H>::PARAMS + DEEP * LstmCell::<H, H>::PARAMS;

    /// Takes the layers in order from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        let first = LstmCell::load(r)?;
        let empty = LstmCell {
            weight_ih: Matrix::F32(&[]),
            weight_hh: Matrix::F32(&[]),
            bias: &[],
        };
        let mut deep = [empty; DEEP];
        for cell in &mut deep {
            *cell = LstmCell::load(r)?;
        }
        Ok(Self { first, deep })
    }

    /// Advances every layer by one input; the output is `state.output()`.
    pub fn step(&self, x: &[f32; IN], state: &mut LstmStackState<H, DEEP>) {
        self.first.step(x, &mut state.first);
        let mut below: &[f32; H] = &state.first.h;
        for (cell, s) in self.deep.iter().zip(state.deep.iter_mut()) {
            cell.step(below, s);
            let s: &LstmLayerState<H> = s;
            below = &s.h;
        }
    }

    /// [`Self::step`] of [`LANES`] inputs and states side by side, each lane the same bits.
    #[inline(always)]
    pub fn step_lanes(&self, x: &Lanes<IN>, state: &mut LstmStackLanes<H, DEEP>) {
        self.first.step_lanes(x, &mut state.first);
        let mut below: &Lanes<H> = &state.first.h;
        for (cell, s) in self.deep.iter().zip(state.deep.iter_mut()) {
            cell.step_lanes(below, s);
            let s: &LstmLayerLanes<H> = s;
            below = &s.h;
        }
    }
}

/// A recurrent policy: an LSTM stack on the observation, then an MLP head on its output.
#[derive(Clone, Copy, Debug)]
pub struct LstmPolicy<'w, const IN: usize, const H: usize, const DEEP: usize, M> {
    lstm: LstmStack<'w, IN, H, DEEP>,
    head: M,
}

impl<'w, const IN: usize, const H: usize, const DEEP: usize, M: Head<'w, H>>
    LstmPolicy<'w, IN, H, DEEP, M>
{
    /// Number of parameters.
    pub const PARAMS: usize = LstmStack::<IN, H, DEEP>::PARAMS + M::PARAMS;
    /// Bytes of activations kept on the stack by one step: the larger of the LSTM cell's gate
    /// pre-activations and the head's activations (their frames do not overlap), plus the
    /// int8 kernels' quantised input ([`I8_SCRATCH_BYTES`], reserved for either dtype).
    pub const SCRATCH_BYTES: usize = (if 4 * H * 4 > M::SCRATCH_BYTES {
        4 * H * 4
    } else {
        M::SCRATCH_BYTES
    }) + I8_SCRATCH_BYTES;

    /// Takes the LSTM layers, then the head, from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            lstm: LstmStack::load(r)?,
            head: M::load(r)?,
        })
    }

    /// Advances the recurrent state by `obs` and returns the Gaussian mean (unclipped).
    pub fn step(&self, obs: &[f32; IN], state: &mut LstmStackState<H, DEEP>) -> [f32; ACTION_DIM] {
        self.lstm.step(obs, state);
        self.head.forward(state.output())
    }

    /// [`Self::step`] of [`LANES`] observations and states side by side, each lane the
    /// same bits (the host's batched rollouts).
    #[inline(always)]
    pub fn step_lanes(
        &self,
        obs: &Lanes<IN>,
        state: &mut LstmStackLanes<H, DEEP>,
    ) -> Lanes<ACTION_DIM> {
        self.lstm.step_lanes(obs, state);
        self.head.forward_lanes(state.output())
    }
}
