//! PPO's two loss heads on a chunked minibatch: the actor's clipped surrogate with the
//! Gaussian log-likelihood, entropy bonus and KL; the critic's clipped value loss.

use super::net::Side;
use crate::batch::{Batch, LN_2PI, Minibatch};
use crate::config::PpoConfig;
use firmware_core::nn::ACTION_DIM;

/// What the actor's pass measures on a minibatch.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ActorStats {
    pub(super) surrogate: f64,
    pub(super) entropy: f64,
    pub(super) kl: f64,
    pub(super) clip_fraction: f64,
}

/// The actor's pass: clipped surrogate, entropy bonus, KL before the step; gradients into
/// `side.grad` (log σ's last).
pub(super) fn actor_pass(side: &mut Side, b: &Batch, mb: &Minibatch, p: &PpoConfig) -> ActorStats {
    let n = mb.samples.len().max(1);
    let sums = actor_pass_part(side, b, mb, p, n);
    finish_actor_pass(side, p, sums, n)
}

/// What a part of a minibatch adds to the actor's statistics (before they are divided by the
/// minibatch's size).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ActorSums {
    surrogate: f64,
    kl: f64,
    clipped: usize,
    sum_log_std: f32,
}

impl ActorSums {
    /// The sums of two parts.
    pub(super) fn plus(self, other: Self) -> Self {
        Self {
            surrogate: self.surrogate + other.surrogate,
            kl: self.kl + other.kl,
            clipped: self.clipped + other.clipped,
            sum_log_std: self.sum_log_std,
        }
    }
}

/// The actor's pass over `mb`, a part of a minibatch of `of` samples (the whole of it, or
/// one thread's share of its windows): the surrogate's gradients scaled for `of` samples
/// into `side.grad`, log σ's without the entropy bonus ([`finish_actor_pass`] adds it once).
pub(super) fn actor_pass_part(
    side: &mut Side,
    b: &Batch,
    mb: &Minibatch,
    p: &PpoConfig,
    of: usize,
) -> ActorSums {
    let ls_at = side.net.mlp_len();
    let log_std: [f32; ACTION_DIM] = core::array::from_fn(|k| side.net.params[ls_at + k]);
    let inv_std = log_std.map(|l| (-l).exp());
    let std_now = log_std.map(f32::exp);
    let sum_log_std: f32 = log_std.iter().sum();
    let norm_const = 0.5 * LN_2PI * ACTION_DIM as f32;
    let inv_n = 1.0 / of.max(1) as f32;
    let (lo, hi) = (1.0 - p.clip, 1.0 + p.clip);
    let mut kl = 0.0f64;
    let mut surrogate = 0.0f64;
    let mut clipped_count = 0usize;
    let mut d_log_std = [0.0f64; ACTION_DIM];
    side.pass(b, mb, |rows, mean, d_mean| {
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
        *g = d as f32;
    }
    ActorSums {
        surrogate,
        kl,
        clipped: clipped_count,
        sum_log_std,
    }
}

/// The entropy bonus's gradient on log σ and the statistics of a minibatch of `n` samples
/// whose parts summed to `sums`.
pub(super) fn finish_actor_pass(
    side: &mut Side,
    p: &PpoConfig,
    sums: ActorSums,
    n: usize,
) -> ActorStats {
    let ls_at = side.net.mlp_len();
    for g in &mut side.grad[ls_at..] {
        *g -= p.entropy_coef;
    }
    let n = n.max(1) as f64;
    ActorStats {
        surrogate: sums.surrogate / n,
        entropy: f64::from(sums.sum_log_std + 0.5 * (1.0 + LN_2PI) * ACTION_DIM as f32),
        kl: sums.kl / n,
        clip_fraction: sums.clipped as f64 / n,
    }
}

/// The critic's pass: the clipped value loss (before its coefficient), gradients of
/// `value_coef ×` it into `side.grad`.
pub(super) fn critic_pass(side: &mut Side, b: &Batch, mb: &Minibatch, p: &PpoConfig) -> f64 {
    let samples = mb.samples.len().max(1);
    let scale = p.value_coef / samples as f32;
    let mut loss = 0.0f64;
    side.pass(b, mb, |rows, v, dv| {
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
    loss / samples as f64
}

pub(super) fn squared(v: &[f32]) -> f64 {
    v.iter().map(|&g| f64::from(g) * f64::from(g)).sum()
}
