//! What PPO needs of a network, as three traits: [`PpoNet`] (its outputs for a minibatch and
//! for a whole rollout), [`PolicyNet`] (a Gaussian policy whose weights are a firmware-core
//! blob payload) and [`ValueNet`] (a value function). The feed-forward networks of rows A-D
//! ([`crate::model`]) and the LSTM networks of rows E-G ([`crate::recurrent`]) implement
//! them beside their definitions; PPO ([`crate::ppo`]) and the run ([`crate::train`]) are
//! written once against the traits.

use crate::batch::{Batch, Minibatch};
use burn::module::Module;
use burn::tensor::{Device, Tensor};
use firmware_core::policy::Architecture;
use rand_chacha::ChaCha8Rng;

/// How PPO runs a network.
pub trait PpoNet: Module + Sync + 'static {
    /// Minibatches are whole env windows (the network carries a state) rather than samples.
    const RECURRENT: bool;
    /// The outputs for `mb`'s samples, one row each in `mb.samples` order (autodiff when
    /// the network is on an autodiff device).
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2>;
    /// The outputs for every sample of `b`; with `last_obs` (the observations after the
    /// window) also the outputs for those and the state to start the next window from
    /// (empty when feed-forward), else both empty.
    fn rollout_outputs(
        &self,
        b: &Batch,
        last_obs: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>);
}

/// A Gaussian policy PPO trains: outputs are the means; σ is state-independent. Its weights
/// map one-to-one onto a firmware-core blob payload.
pub trait PolicyNet: PpoNet + Sized {
    /// A fresh actor of `arch` with σ = `init_std`, initialised from `rng` as PyTorch
    /// initialises the same modules.
    fn fresh(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self;
    /// log σ per action (a parameter).
    fn log_std(&self) -> Tensor<1>;
    /// σ per action.
    fn std(&self) -> Vec<f32>;
    /// The weights in firmware-core payload order (`Architecture::tensors`).
    fn payload(&self) -> Vec<f32>;
    /// The actor holding `payload` with σ = `std`; `None` when they do not fit `arch`.
    fn from_payload(
        arch: &Architecture,
        payload: &[f32],
        std: &[f32],
        device: &Device,
    ) -> Option<Self>;
    /// The same actor with its output bias set to `action` on every motor: the mean action
    /// of an all-zero hidden layer (e.g. the hover action, so that the first rollouts hover
    /// instead of falling).
    fn with_output_bias(self, action: f32) -> Self;
    /// The same actor with every σ clamped to at most `max_std`, the parameter keeping its
    /// identity (and so its Adam state).
    fn with_std_at_most(self, max_std: f32) -> Self;
}

/// A value function PPO trains.
pub trait ValueNet: PpoNet {
    /// A fresh critic with `arch`'s shape and one output, initialised from `rng`.
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self;
}
