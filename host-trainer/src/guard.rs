//! The guard (`[guard]`, not in the paper; docs/journal/stage1.md "Why PPO leaves the
//! student"): a
//! line search on the measured return after each PPO update. The updated actor, and if it
//! is worse the update scaled by 1/2 and 1/4, must reach at least the old actor's reward per
//! step on one test rollout with common random numbers (the same seeds for environments and
//! action noise for both); if none does, the actor stays as it was.

use crate::config::{Guard, TrainConfig};
use crate::error::TrainError;
use crate::nets::{PolicyNet, ValueNet};
use crate::ppo::Learner;
use crate::rng::generator;
use crate::rollout::{Rollout, collect_rollout};
use firmware_core::policy::{Architecture, Policy};
use sitl::env::VecEnv;

/// Reward per step of the Gaussian policy with weights `payload` and σ `std` on the guard's
/// test rollout, the environments and the action noise seeded by `seed`.
pub fn measured_return(
    payload: &[f32],
    std: &[f32],
    arch: &Architecture,
    config: &TrainConfig,
    guard: &Guard,
    seed: u64,
) -> Result<f64, TrainError> {
    let policy = Policy::from_payload(arch, payload)
        .map_err(|e| TrainError::Export(format!("actor does not load as a blob: {e}")))?;
    let mut c = config.env_config(seed);
    c.num_envs = guard.envs;
    let mut env = VecEnv::new(c)?;
    let mut rng = generator(seed, 7);
    let mut rollout = Rollout::new(guard.envs, env.obs_dim());
    if guard.warmup_steps > 0 {
        collect_rollout(
            &mut env,
            &policy,
            std,
            guard.warmup_steps,
            &mut rng,
            &mut rollout,
            |_, _| {},
        )?;
    }
    let (mut sum, mut count) = (0.0f64, 0usize);
    collect_rollout(
        &mut env,
        &policy,
        std,
        guard.steps,
        &mut rng,
        &mut rollout,
        |r, _| {
            sum += r.iter().map(|&x| f64::from(x)).sum::<f64>();
            count += r.len();
        },
    )?;
    Ok(sum / count.max(1) as f64)
}

/// The guard's line search after an update from `before` (weights, log σ): keeps the
/// largest of 1, 1/2, 1/4 of the update whose measured return is at least the old one's,
/// else restores `before`, resets the actor's Adam state and halves the learning rate.
/// Returns (share kept, return before, return kept).
pub(crate) fn guard_update<A: PolicyNet, C: ValueNet>(
    learner: &mut Learner<A, C>,
    before: (&[f32], &[f32]),
    arch: &Architecture,
    config: &TrainConfig,
    guard: &Guard,
    seed: u64,
) -> Result<(f64, f64, f64), TrainError> {
    let (old_w, old_std) = before;
    let new_w = learner.actor.payload();
    let new_std = learner.actor.std();
    let base = measured_return(old_w, old_std, arch, config, guard, seed)?;
    for share in [1.0f32, 0.5, 0.25] {
        let w: Vec<f32> = old_w
            .iter()
            .zip(&new_w)
            .map(|(a, b)| a + share * (b - a))
            .collect();
        let std: Vec<f32> = old_std
            .iter()
            .zip(&new_std)
            .map(|(a, b)| (a.ln() + share * (b.ln() - a.ln())).exp())
            .collect();
        let r = measured_return(&w, &std, arch, config, guard, seed)?;
        if r >= base {
            if share < 1.0 {
                learner.actor = A::from_payload(arch, &w, &std, &learner.device)
                    .ok_or_else(|| TrainError::Export("guard: weights do not fit".into()))?;
            }
            return Ok((f64::from(share), base, r));
        }
    }
    learner.actor = A::from_payload(arch, old_w, old_std, &learner.device)
        .ok_or_else(|| TrainError::Export("guard: weights do not fit".into()))?;
    learner.reset_actor_optim();
    learner.learning_rate = (learner.learning_rate / 2.0).max(config.ppo.min_learning_rate);
    Ok((0.0, base, base))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::actor_from_blob;
    use crate::model::{Actor, Critic};
    use crate::rng::{init_rng, normal};
    use burn::tensor::Device;
    use std::path::Path;

    /// stage1_finetune.toml with a small guard, and the shipped student as its actor.
    fn student_learner() -> (TrainConfig, Architecture, Learner) {
        let mut config =
            TrainConfig::parse(include_str!("../configs/experiments/stage1_finetune.toml"))
                .unwrap();
        config.guard = Some(Guard {
            envs: 64,
            warmup_steps: 10,
            steps: 100,
        });
        let arch = config.architecture().unwrap();
        let device = Device::flex().autodiff();
        let blob = Path::new(env!("CARGO_MANIFEST_DIR")).join("../policies/stage1_imitation.blob");
        let actor = actor_from_blob(&blob, &arch, &config, &device).unwrap();
        let critic = Critic::fresh(&arch, &mut init_rng(1), &device);
        (config, arch, Learner::new(actor, critic, 1e-4, device))
    }

    #[test]
    fn the_guard_rejects_an_update_that_lowers_the_measured_return() {
        let (config, arch, mut learner) = student_learner();
        let guard = config.guard.clone().unwrap();
        let (w, std) = (learner.actor.payload(), learner.actor.std());
        // The same seed measures the same return: the comparison is common random numbers.
        let r = measured_return(&w, &std, &arch, &config, &guard, 5).unwrap();
        assert_eq!(
            r,
            measured_return(&w, &std, &arch, &config, &guard, 5).unwrap()
        );
        // An "update" that adds ±1e-2 to every weight (it breaks the student): rejected, the
        // student restored, the learning rate halved.
        let mut rng = generator(3, 0);
        let broken: Vec<f32> = w.iter().map(|v| v + 1e-2 * normal(&mut rng)).collect();
        learner.actor = Actor::from_payload(&arch, &broken, &std, &learner.device).unwrap();
        let (share, before, after) =
            guard_update(&mut learner, (&w, &std), &arch, &config, &guard, 5).unwrap();
        assert_eq!(share, 0.0, "before {before}, after {after}");
        assert_eq!(learner.actor.payload(), w);
        assert_eq!(learner.learning_rate, 5e-5);
        // No change at all is no loss: kept whole.
        let (share, before, after) =
            guard_update(&mut learner, (&w, &std), &arch, &config, &guard, 6).unwrap();
        assert_eq!((share, before), (1.0, after));
    }
}
