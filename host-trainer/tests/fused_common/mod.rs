//! What the fused update's parity tests (`fused.rs`, `fused_recurrent.rs`,
//! `privileged_critic.rs`) share: the error measure, the networks' flat parameters, and the
//! comparisons of a prepared batch, of a step's statistics and of the networks after it.

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::Tensor;
use host_trainer::batch::Batch;
use host_trainer::config::{PpoConfig, UpdateKind};
use host_trainer::model::values;
use host_trainer::nets::{PolicyNet, PpoNet};
use host_trainer::ppo::{Learner, UpdateStats};
use host_trainer::rollout::Rollout;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The PPO settings of the parity tests (2 epochs × 2 minibatches, entropy and KL on) with
/// `update`.
pub fn params(update: UpdateKind) -> PpoConfig {
    PpoConfig {
        epochs: 2,
        minibatches: 2,
        value_coef: 0.7,
        entropy_coef: 0.01,
        learning_rate: 1e-4,
        desired_kl: Some(0.01),
        update,
        ..PpoConfig::default()
    }
}

/// The batch `burn` builds from `r`, its old log-probabilities and values moved by up to
/// ±0.5 so that a share of the ratios and of the values starts outside the clip range.
/// (`fused.rs` builds its feed-forward batches sample by sample instead.)
#[allow(dead_code)]
pub fn clip_crossing_batch<A: PolicyNet, C: PpoNet>(
    l: &Learner<A, C>,
    r: &Rollout,
    seed: u64,
) -> Batch {
    let mut b = l.prepare(r, &params(UpdateKind::Burn));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for lp in &mut b.old_log_prob {
        *lp += rng.random_range(-0.5..0.5);
    }
    for v in &mut b.old_values {
        *v += rng.random_range(-0.5..0.5);
    }
    b
}

/// The largest `|a − b|` relative to `max |b|` over the vector.
pub fn relative_error(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-12);
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() / scale)
        .fold(0.0, f32::max)
}

/// The batch `prepare` built on the fused path against `burn`'s: the old means, values and
/// log-probabilities, the returns and the advantages, each the same to 1e-5 (relative).
pub fn assert_prepared_close(fused: &Batch, burn: &Batch, what: &str) {
    for (name, a, b) in [
        ("old_mean", &fused.old_mean, &burn.old_mean),
        ("old_values", &fused.old_values, &burn.old_values),
        ("old_log_prob", &fused.old_log_prob, &burn.old_log_prob),
        ("returns", &fused.returns, &burn.returns),
        ("advantages", &fused.advantages, &burn.advantages),
    ] {
        let e = relative_error(a, b);
        assert!(e < 1e-5, "{what} {name}: relative error {e:e}");
    }
}

/// Every parameter's flat values in `burn`'s visiting order.
pub fn flat<M: Module>(m: &M) -> Vec<f32> {
    struct Collect(Vec<f32>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.extend(values(param.val()));
        }
    }
    let mut c = Collect(Vec::new());
    m.visit(&mut c);
    c.0
}

/// A fused step's statistics against `burn`'s: the same to 1e-5 (relative, or absolute
/// below 1e-3), the same learning rate and skips.
pub fn assert_stats_close(a: &UpdateStats, b: &UpdateStats) {
    let close = |x: f64, y: f64, what: &str| {
        assert!(
            (x - y).abs() <= 1e-5 * y.abs().max(1e-3),
            "{what}: fused {x} burn {y}"
        );
    };
    close(a.surrogate_loss, b.surrogate_loss, "surrogate");
    close(a.value_loss, b.value_loss, "value loss");
    close(a.entropy, b.entropy, "entropy");
    close(a.kl, b.kl, "kl");
    close(a.clip_fraction, b.clip_fraction, "clip fraction");
    close(a.grad_norm, b.grad_norm, "grad norm");
    assert_eq!(a.learning_rate, b.learning_rate);
    assert_eq!(a.skipped, b.skipped);
}

/// Parameters after the same steps taken by both updates: no value apart by `tol` or more.
pub fn assert_networks_close<A: Module, C: Module>(
    fused: &Learner<A, C>,
    burn: &Learner<A, C>,
    tol: f32,
) {
    for (name, a, b) in [
        ("actor", flat(&fused.actor), flat(&burn.actor)),
        ("critic", flat(&fused.critic), flat(&burn.critic)),
    ] {
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < tol, "{name}: largest difference {worst:e}");
    }
}
