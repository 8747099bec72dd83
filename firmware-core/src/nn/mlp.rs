//! The fully connected layer, the MLP heads and the feed-forward policy.
//!
//! One generic head, [`Mlp`], over a chain of layers: [`Hidden`] layers (a [`Linear`] layer,
//! then tanh) ending in the output [`Linear`] layer. [`Mlp2`], [`Mlp3`] and [`Mlp4`] name the
//! chains of Table 1. The chain is nested types, so every width stays a const generic and
//! the forward pass, inlined into one function, is the operations of the layers in order.

use super::kernels::{Matrix, tanh_in_place};
use super::lanes::{dot_lanes, lane, set_lane, tanh_lanes};
use super::{ACTION_DIM, LANES, Lanes, WeightReader};
use crate::format::BlobError;

/// A fully connected layer `y = W x + b` viewing `[OUT][IN]` weights and `[OUT]` biases.
#[derive(Clone, Copy, Debug)]
pub struct Linear<'w, const IN: usize, const OUT: usize> {
    weight: Matrix<'w>,
    bias: &'w [f32],
}

impl<'w, const IN: usize, const OUT: usize> Linear<'w, IN, OUT> {
    /// Number of parameters.
    pub const PARAMS: usize = IN * OUT + OUT;

    /// Takes the layer's weights, then biases, from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        let weight = r.take_matrix(OUT, IN)?;
        let bias = r.take(OUT)?;
        Ok(Self { weight, bias })
    }

    /// `y = W x + b`.
    #[inline]
    pub fn forward(&self, x: &[f32; IN], y: &mut [f32; OUT]) {
        y.fill(0.0);
        self.weight.mul_add(x, y);
        for (yo, b) in y.iter_mut().zip(self.bias) {
            *yo += b;
        }
    }

    /// [`Self::forward`] of [`LANES`] inputs side by side, each lane the same bits.
    #[inline(always)]
    pub fn forward_lanes(&self, x: &Lanes<IN>, y: &mut Lanes<OUT>) {
        match self.weight {
            Matrix::F32(w) => {
                for ((yo, row), b) in y.iter_mut().zip(w.chunks_exact(IN.max(1))).zip(self.bias) {
                    let d = dot_lanes(row, x);
                    for (yl, dl) in yo.iter_mut().zip(d) {
                        // `forward`'s order: 0 + W x, then + b.
                        *yl = (0.0 + dl) + b;
                    }
                }
            }
            // int8 quantises each input with its own scale: lane by lane.
            Matrix::I8 { .. } => {
                for l in 0..LANES {
                    let mut out = [0.0f32; OUT];
                    self.forward(&lane(x, l), &mut out);
                    set_lane(y, l, &out);
                }
            }
        }
    }
}

/// An MLP head: its forward pass from `IN` features to the [`ACTION_DIM`] outputs.
pub trait Head<'w, const IN: usize>: Sized {
    /// Number of parameters.
    const PARAMS: usize;
    /// Bytes of activations the forward pass keeps on the stack.
    const SCRATCH_BYTES: usize;
    /// Takes the layers in order from `r`.
    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError>;
    /// The output (the Gaussian mean, not yet clipped).
    fn forward(&self, x: &[f32; IN]) -> [f32; ACTION_DIM];
    /// [`Self::forward`] of [`LANES`] inputs side by side, each lane the same bits (the
    /// host's batched inference; unused on the flight controller).
    #[inline(always)]
    fn forward_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        let mut y = [[0.0f32; LANES]; ACTION_DIM];
        for l in 0..LANES {
            set_lane(&mut y, l, &self.forward(&lane(x, l)));
        }
        y
    }
}

/// The layers of an MLP head from `IN` features to the [`ACTION_DIM`] outputs, run by
/// [`Mlp`]: [`Hidden`] layers ending in the output [`Linear`] layer.
pub trait Layers<'w, const IN: usize>: Sized {
    /// Number of parameters.
    const PARAMS: usize;
    /// Bytes of activations the forward pass keeps on the stack.
    const SCRATCH_BYTES: usize;
    /// Takes the layers in order from `r`.
    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError>;
    /// The output for `x` (inlined into [`Mlp`]'s forward pass).
    fn apply(&self, x: &[f32; IN]) -> [f32; ACTION_DIM];
    /// [`Self::apply`] of [`LANES`] inputs side by side, each lane the same bits.
    fn apply_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM>;
}

/// A hidden layer of an MLP head: [`Linear<IN, OUT>`] followed by tanh, then the layers
/// `Next` on its `OUT` activations.
#[derive(Clone, Copy, Debug)]
pub struct Hidden<'w, const IN: usize, const OUT: usize, Next> {
    layer: Linear<'w, IN, OUT>,
    next: Next,
}

impl<'w, const IN: usize, const OUT: usize, Next: Layers<'w, OUT>> Layers<'w, IN>
    for Hidden<'w, IN, OUT, Next>
{
    const PARAMS: usize = Linear::<IN, OUT>::PARAMS + Next::PARAMS;
    const SCRATCH_BYTES: usize = OUT * 4 + Next::SCRATCH_BYTES;

    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            layer: Linear::load(r)?,
            next: Next::load(r)?,
        })
    }

    #[inline(always)]
    fn apply(&self, x: &[f32; IN]) -> [f32; ACTION_DIM] {
        let mut a = [0.0f32; OUT];
        self.layer.forward(x, &mut a);
        tanh_in_place(&mut a);
        self.next.apply(&a)
    }

    #[inline(always)]
    fn apply_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        let mut a = [[0.0f32; LANES]; OUT];
        self.layer.forward_lanes(x, &mut a);
        tanh_lanes(&mut a);
        self.next.apply_lanes(&a)
    }
}

/// The output layer of an MLP head: linear, no activation. (Its items are the inherent
/// ones of [`Linear`], which path resolution picks before the trait's.)
impl<'w, const IN: usize> Layers<'w, IN> for Linear<'w, IN, ACTION_DIM> {
    const PARAMS: usize = Linear::<IN, ACTION_DIM>::PARAMS;
    const SCRATCH_BYTES: usize = ACTION_DIM * 4;

    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Linear::load(r)
    }

    #[inline(always)]
    fn apply(&self, x: &[f32; IN]) -> [f32; ACTION_DIM] {
        let mut y = [0.0f32; ACTION_DIM];
        self.forward(x, &mut y);
        y
    }

    #[inline(always)]
    fn apply_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        let mut y = [[0.0f32; LANES]; ACTION_DIM];
        self.forward_lanes(x, &mut y);
        y
    }
}

/// An MLP head: its [`Layers`] `L` in one out-of-line forward pass (every activation in the
/// one stack frame, as [`Head::SCRATCH_BYTES`] counts them).
#[derive(Clone, Copy, Debug)]
pub struct Mlp<L> {
    layers: L,
}

impl<'w, const IN: usize, L: Layers<'w, IN>> Head<'w, IN> for Mlp<L> {
    const PARAMS: usize = L::PARAMS;
    const SCRATCH_BYTES: usize = L::SCRATCH_BYTES;

    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            layers: L::load(r)?,
        })
    }

    #[inline(never)]
    fn forward(&self, x: &[f32; IN]) -> [f32; ACTION_DIM] {
        self.layers.apply(x)
    }

    #[inline(always)]
    fn forward_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        self.layers.apply_lanes(x)
    }
}

/// MLP head with two tanh hidden layers (Table 1 rows A, B: 2 × 128).
pub type Mlp2<'w, const IN: usize, const H1: usize, const H2: usize> =
    Mlp<Hidden<'w, IN, H1, Hidden<'w, H1, H2, Linear<'w, H2, ACTION_DIM>>>>;

/// MLP head with three tanh hidden layers (row F: 256, 128, 128).
pub type Mlp3<'w, const IN: usize, const H1: usize, const H2: usize, const H3: usize> =
    Mlp<Hidden<'w, IN, H1, Hidden<'w, H1, H2, Hidden<'w, H2, H3, Linear<'w, H3, ACTION_DIM>>>>>;

/// MLP head with four tanh hidden layers (rows C, D, E, G: 256, 128, 128, 64).
pub type Mlp4<
    'w,
    const IN: usize,
    const H1: usize,
    const H2: usize,
    const H3: usize,
    const H4: usize,
> = Mlp<
    Hidden<
        'w,
        IN,
        H1,
        Hidden<'w, H1, H2, Hidden<'w, H2, H3, Hidden<'w, H3, H4, Linear<'w, H4, ACTION_DIM>>>>,
    >,
>;

/// A feed-forward policy: an MLP head on the observation.
#[derive(Clone, Copy, Debug)]
pub struct MlpPolicy<M> {
    head: M,
}

impl<M> MlpPolicy<M> {
    /// Takes the head's weights from `r`.
    pub fn load<'w, const IN: usize>(r: &mut WeightReader<'w>) -> Result<Self, BlobError>
    where
        M: Head<'w, IN>,
    {
        Ok(Self { head: M::load(r)? })
    }

    /// The Gaussian mean for observation `obs` (unclipped).
    pub fn forward<'w, const IN: usize>(&self, obs: &[f32; IN]) -> [f32; ACTION_DIM]
    where
        M: Head<'w, IN>,
    {
        self.head.forward(obs)
    }

    /// [`Self::forward`] of [`LANES`] observations side by side, each lane the same bits.
    #[inline(always)]
    pub fn forward_lanes<'w, const IN: usize>(&self, obs: &Lanes<IN>) -> Lanes<ACTION_DIM>
    where
        M: Head<'w, IN>,
    {
        self.head.forward_lanes(obs)
    }
}
