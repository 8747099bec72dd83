//! The configurations in code: every section's `Default` (the paper's stage 1, RSL-RL's PPO
//! settings) and the named presets of whole runs, [`TrainConfig::paper`] and
//! [`TrainConfig::ours`] (`host-trainer/tests/config.rs` holds each equal to its TOML file).

use super::{
    CriticKind, KeepBestBy, PassDecay, PpoConfig, RunConfig, Selection, StdDecay, TrainConfig,
    UpdateKind, WarmStart, default_eval_every, default_eval_races, default_max_learning_rate,
    default_min_learning_rate, one,
};
use sitl::env::EnvConfig;

impl Default for TrainConfig {
    /// The paper's stage-1 run: [`TrainConfig::paper`].
    fn default() -> Self {
        Self::paper()
    }
}

impl TrainConfig {
    /// The paper's stage-1 run (`configs/stage1_paper.toml`): row A from a random network,
    /// 8,192 envs spawned at the paper's stage-1 spawn, 15 s episodes, 100 steps per env,
    /// 5 epochs of 4 minibatches, lr 1e-4 with the adaptive KL target 0.01, entropy 0.01,
    /// σ₀ 1, 1,500 iterations (1.2 billion samples): far beyond two CPU cores.
    pub fn paper() -> Self {
        Self {
            run: RunConfig {
                name: "stage1-paper".into(),
                iterations: 1500,
                checkpoint_every: 50,
                ..RunConfig::default()
            },
            env: EnvConfig::paper(8192),
            ppo: PpoConfig::default(),
            warm_start: None,
            pass_decay: None,
            randomize_ramp: None,
            guard: None,
            opponent_curriculum: Vec::new(),
        }
        .with_env_derived()
    }

    /// `self` with `env.layout` and `env.seed` set from `run` as a parsed config has them.
    fn with_env_derived(mut self) -> Self {
        self.env = self.env_config(self.run.seed);
        self
    }

    /// This project's nominal stage-1 pipeline (`configs/experiments/stage1_nominal.toml`,
    /// `configs/stage1.toml` until it randomised the ego), PPO from a random network:
    /// 512 envs × 100 steps spawned along the track at up to 8 m/s (a fifth at the paper's
    /// spawn, 30 % replaying states after gate passes), the figure-8 folded by its mirror
    /// symmetry, the own velocity observed at 12 m/s full scale, lr 3e-4, σ₀ 0.3 under a
    /// ceiling falling from 1 to 0.1 over iterations 800-2000, a hover-biased output, crash
    /// weight 1 and the pass weight falling from 1 to 0 over iterations 1700-2000; 2,500
    /// iterations (128 M samples), exporting the actor of iterations 2,000-2,500 that flies
    /// best from 100 validation spawns along the track.
    pub fn ours() -> Self {
        Self {
            run: RunConfig {
                name: "stage1".into(),
                iterations: 2500,
                checkpoint_every: 10,
                eval_every: 20,
                keep_best: true,
                select: Some(Selection {
                    spawn: sitl::referee::SpawnMode::AlongTrack,
                    episodes: 100,
                    seed: 7,
                    from_iteration: 2000,
                    perturb: Vec::new(),
                    jitter: None,
                    referee_floor: None,
                    race_bar: false,
                }),
                ..RunConfig::default()
            },
            env: EnvConfig::stage1(512),
            ppo: PpoConfig {
                learning_rate: 3e-4,
                max_std: Some(1.0),
                max_std_decay: Some(StdDecay {
                    final_std: 0.1,
                    from_iteration: 800,
                    to_iteration: 2000,
                }),
                init_std: 0.3,
                init_hover: true,
                ..PpoConfig::default()
            },
            warm_start: None,
            pass_decay: Some(PassDecay {
                final_weight: 0.0,
                from_iteration: 1700,
                to_iteration: 2000,
            }),
            randomize_ramp: None,
            guard: None,
            opponent_curriculum: Vec::new(),
        }
        .with_env_derived()
    }
}

impl Default for RunConfig {
    /// Row A, seed 1, 1,500 iterations, a checkpoint every 50 and an evaluation every 10,
    /// 4 evaluation races on seed 0, the last actor exported.
    fn default() -> Self {
        Self {
            name: "stage1".into(),
            row: 'A',
            seed: 1,
            iterations: 1500,
            checkpoint_every: 50,
            eval_every: default_eval_every(),
            eval_races: default_eval_races(),
            eval_seed: 0,
            eval_jitter: false,
            keep_best: false,
            keep_best_by: KeepBestBy::Success,
            select: None,
        }
    }
}

impl Default for PpoConfig {
    /// RSL-RL's and the paper's stage 1: 100 steps per env, 5 epochs × 4 minibatches, clip
    /// 0.2, γ 0.99, λ 0.95, value coefficient 1, entropy 0.01, lr 1e-4 adapted to a KL of
    /// 0.01 (floor 1e-5), gradient norm 1, σ₀ 1, PyTorch's initialisation.
    fn default() -> Self {
        Self {
            steps_per_env: 100,
            epochs: 5,
            minibatches: 4,
            clip: 0.2,
            gamma: 0.99,
            lambda: 0.95,
            value_coef: 1.0,
            entropy_coef: 0.01,
            learning_rate: 1e-4,
            desired_kl: Some(0.01),
            max_grad_norm: 1.0,
            min_learning_rate: default_min_learning_rate(),
            max_learning_rate: default_max_learning_rate(),
            max_std: None,
            max_std_decay: None,
            critic_learning_rate: None,
            lstm_learning_rate_scale: None,
            init_std: 1.0,
            init_hover: false,
            update: UpdateKind::Auto,
            critic: CriticKind::ActorShaped,
        }
    }
}

impl Default for WarmStart {
    /// The stage-1 student's (`configs/experiments/stage1_finetune.toml`, `configs/experiments/stage1_imitation.toml`): 40 DAgger rounds of 50 steps of the
    /// classical baseline at 9 m/s, 3 epochs of minibatches of 2,048 over the last 400,000
    /// samples at lr 1e-3, the student's actions with σ 0.1 noise, then 30 critic-only
    /// iterations; no refinement, no round selection.
    fn default() -> Self {
        Self {
            teacher_cruise_mps: 9.0,
            teacher_blob: None,
            student: None,
            transplant: false,
            rounds: 40,
            steps_per_env: 50,
            epochs: 3,
            minibatch: 2048,
            max_samples: 400_000,
            learning_rate: 1e-3,
            learning_rate_final: None,
            teacher_share_start: one(),
            student_noise_std: 0.1,
            critic_iterations: 30,
            keep_best_round: false,
            clamp_labels: false,
            refine: Vec::new(),
        }
    }
}
