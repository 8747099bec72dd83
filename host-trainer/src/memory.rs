//! What a run will hold in memory, estimated from its config before anything is allocated,
//! and checked against what the machine has (issue "faults": `steps_per_env = 1e8` used to
//! grow until the kernel killed the trainer).
//!
//! The estimate counts the buffers that grow with the config, with generous factors, plus a
//! fixed base (the binary, the networks, Adam, thread stacks): the rollout and its training
//! batch (per sample: the observation twice, the action, mean, log-probability, value,
//! return, advantage, reward and flags), the update's activations for one minibatch (every
//! hidden unit of actor and critic, forward and backward, with a factor for the autodiff
//! tape), the full-batch forward pass of `prepare`, the guard's test rollouts and the warm
//! start's data set. Calibrated on `configs/stage1.toml`: estimated 0.6 GiB, measured 0.5 GiB
//! resident (2-vCPU Intel Xeon, 2026-12-05).

use crate::config::TrainConfig;
use crate::error::TrainError;
use firmware_core::policy::Architecture;

/// Memory every run holds whatever its size (bytes): code, networks, optimiser, threads.
pub const BASE_BYTES: u64 = 256 << 20;

/// Bytes of one hidden unit's value per sample of a minibatch in the update: the forward
/// activation, its gradient, and the autodiff tape's copies.
const BYTES_PER_UNIT: u64 = 4 * 6;

/// A run's estimated memory, by part (bytes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryEstimate {
    /// Samples per iteration (`num_envs × steps_per_env`).
    pub samples: u64,
    /// The rollout and the training batch made from it.
    pub buffers: u64,
    /// The update's activations (one minibatch) and `prepare`'s full-batch forward pass.
    pub update: u64,
    /// The guard's and the warm start's rollouts and data.
    pub extras: u64,
}

impl MemoryEstimate {
    /// The estimate for `config` with networks `arch`.
    pub fn of(config: &TrainConfig, arch: &Architecture) -> Self {
        let obs = u64::from(arch.obs_dim);
        let envs = config.env.num_envs as u64;
        let samples = envs.saturating_mul(config.ppo.steps_per_env as u64);
        // Rollout: obs, action (4), reward, 2 flags; batch: obs, action, mean (4), log-prob,
        // value, return, advantage. f32 = 4 bytes.
        let per_sample = 4 * (2 * obs + 4 + 1 + 4 + 4 + 1 + 4) + 2;
        let buffers = samples.saturating_mul(per_sample);
        let units = hidden_units(arch);
        let minibatch = samples / config.ppo.minibatches.max(1) as u64;
        let update = minibatch
            .saturating_mul(units)
            .saturating_mul(BYTES_PER_UNIT)
            .saturating_add(samples.saturating_mul(units).saturating_mul(4));
        let mut extras = 0u64;
        if let Some(g) = &config.guard {
            let steps = (g.warmup_steps + g.steps) as u64;
            extras = extras.saturating_add(
                (g.envs as u64)
                    .saturating_mul(steps)
                    .saturating_mul(per_sample),
            );
        }
        if let Some(w) = &config.warm_start {
            let rollout = envs
                .saturating_mul(w.steps_per_env as u64)
                .saturating_mul(per_sample);
            let data = (w.max_samples as u64).saturating_mul(4 * (obs + 4));
            let fit = (w.minibatch as u64)
                .saturating_mul(units)
                .saturating_mul(BYTES_PER_UNIT);
            extras = extras
                .saturating_add(rollout)
                .saturating_add(data)
                .saturating_add(fit);
        }
        Self {
            samples,
            buffers,
            update,
            extras,
        }
    }

    /// All of it, with [`BASE_BYTES`].
    pub fn total(&self) -> u64 {
        BASE_BYTES
            .saturating_add(self.buffers)
            .saturating_add(self.update)
            .saturating_add(self.extras)
    }

    /// A clear error when the estimate exceeds `available` bytes; `None` when it fits.
    pub fn refusal(&self, config: &TrainConfig, available: u64) -> Option<TrainError> {
        let gib = |b: u64| b as f64 / f64::from(1u32 << 30);
        (self.total() > available).then(|| {
            TrainError::Config(format!(
                "this run needs about {:.1} GiB ({} envs x {} steps = {} samples per iteration: {:.1} GiB of rollout and batch, {:.1} GiB for the update, {:.1} GiB for the guard and warm start), and {:.1} GiB is available; lower env.num_envs or ppo.steps_per_env",
                gib(self.total()),
                config.env.num_envs,
                config.ppo.steps_per_env,
                self.samples,
                gib(self.buffers),
                gib(self.update),
                gib(self.extras),
                gib(available)
            ))
        })
    }
}

/// Hidden units of actor and critic together, per sample (the LSTM's gates, cell and
/// output per layer, then the MLP head).
fn hidden_units(arch: &Architecture) -> u64 {
    let lstm = u64::from(arch.lstm_layers) * 6 * u64::from(arch.lstm_hidden);
    let mlp: u64 = arch.mlp_hidden.iter().map(|&w| u64::from(w)).sum();
    2 * (lstm + mlp)
}

/// The memory this machine has available now (Linux `MemAvailable`, bytes); `None` where it
/// cannot be read (another OS), when the check is skipped.
pub fn available_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// Refuses `config` when its estimate exceeds the memory available now.
pub fn check(config: &TrainConfig, arch: &Architecture) -> Result<(), TrainError> {
    let Some(available) = available_bytes() else {
        return Ok(());
    };
    match MemoryEstimate::of(config, arch).refusal(config, available) {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(text: &str) -> (TrainConfig, Architecture) {
        let c = TrainConfig::parse(text).unwrap();
        let a = c.architecture().unwrap();
        (c, a)
    }

    #[test]
    fn the_shipped_configs_fit_and_a_huge_rollout_does_not() {
        let (c, a) = config(include_str!("../configs/stage1.toml"));
        let e = MemoryEstimate::of(&c, &a);
        assert_eq!(e.samples, 51_200);
        // Measured 0.5 GiB resident; the estimate is near it and above it.
        let gib = e.total() as f64 / f64::from(1u32 << 30);
        assert!((0.5..1.5).contains(&gib), "{gib} GiB");
        assert!(e.refusal(&c, 4 << 30).is_none());

        let (mut c, a) = config(include_str!("../configs/stage2_G.toml"));
        assert!(MemoryEstimate::of(&c, &a).refusal(&c, 8 << 30).is_none());
        c.ppo.steps_per_env = 100_000_000;
        let e = MemoryEstimate::of(&c, &a);
        let why = e.refusal(&c, 24 << 30).unwrap().to_string();
        assert!(why.contains("steps = 12800000000 samples"), "{why}");
        assert!(
            why.contains("lower env.num_envs or ppo.steps_per_env"),
            "{why}"
        );
    }

    #[test]
    fn available_memory_is_read_here() {
        if cfg!(target_os = "linux") {
            assert!(available_bytes().is_some_and(|b| b > 64 << 20));
        }
    }
}
