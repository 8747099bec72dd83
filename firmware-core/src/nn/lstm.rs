//! The LSTM layers, their stack and the recurrent policy (an LSTM stack, then an MLP head).

use super::kernels::{Matrix, dot, sigmoid, tanh};
use super::mlp::Head;
use super::{ACTION_DIM, I8_SCRATCH_BYTES, WeightReader};
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
}
