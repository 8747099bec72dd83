//! What one PPO update reports ([`UpdateStats`]) and how its learning rate adapts to the
//! measured KL ([`adapt_learning_rate`]): shared by burn's update ([`crate::ppo`]) and the
//! fused CPU update ([`crate::fused`]), which are otherwise independent.

use crate::config::PpoConfig;
use serde::{Deserialize, Serialize};

/// Statistics of one update, averaged over its minibatches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateStats {
    /// Clipped surrogate loss.
    pub surrogate_loss: f64,
    /// Clipped value loss (before its coefficient).
    pub value_loss: f64,
    /// Policy entropy (nats).
    pub entropy: f64,
    /// KL(π_old ‖ π) measured before each step.
    pub kl: f64,
    /// Fraction of samples whose ratio left [1 − ε, 1 + ε].
    pub clip_fraction: f64,
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// Learning rate after the update.
    pub learning_rate: f64,
    /// Minibatches skipped because a loss or the gradient norm was not finite (the networks
    /// are left as they were). `skipped_minibatches` in `metrics.jsonl`.
    #[serde(rename = "skipped_minibatches", default)]
    pub skipped: u32,
}

/// The adaptive learning rate after a step that measured `kl` (RSL-RL): divided by 1.5 above
/// twice the target (floor `min_learning_rate`), multiplied by 1.5 below half of it (cap
/// 1e-2); unchanged without a target.
pub fn adapt_learning_rate(lr: f64, kl: f64, p: &PpoConfig) -> f64 {
    match p.desired_kl {
        Some(target) if kl > 2.0 * target => (lr / 1.5).max(p.min_learning_rate),
        Some(target) if kl < target / 2.0 && kl > 0.0 => (lr * 1.5).min(p.max_learning_rate),
        _ => lr,
    }
}
