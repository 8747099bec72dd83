//! Is PPO's policy gradient signal or noise at our batch size? Takes a run's latest
//! checkpoint (actor and its warmed-up critic), collects K independent rollouts of the
//! run's size from differently seeded environments, computes the actor's gradient on each
//! (the direction the first Adam step of an update follows), and compares them.
//!
//! If the K estimates g_k share a true gradient s and carry independent noise n_k of variance
//! σ²/B at B samples each, the mean cosine between two of them is c = |s|² / (|s|² + σ²/B),
//! so a batch of B·(1 − c)/c samples would make signal and noise equal. Also prints the
//! critic's explained variance on each rollout.
//!
//! Then the question that matters: is that common direction uphill? The example steps the
//! actor along the PPO update direction of all K rollouts together (plain gradient steps of
//! per-weight RMS ε, both signs) and measures the reward per step of each stepped actor on
//! one long rollout with common random numbers (the same environment seeds and action
//! noise for every actor), as PPO's objective sees it.
//!
//! `cargo run --release -p host-trainer --example gradient_snr -- runs/stage1_imitation [K] [LAMBDA]`
//! (the run from `host-trainer train --config host-trainer/configs/experiments/stage1_imitation.toml
//! --out runs/stage1_imitation`).

use burn::optim::SgdConfig;
use firmware_core::policy::Architecture;
use firmware_core::policy::Policy;
use host_trainer::batch::Batch;
use host_trainer::config::{Guard, TrainConfig};
use host_trainer::guard::measured_return;
use host_trainer::latest::checkpoint_learner;
use host_trainer::nets::PolicyNet;
use host_trainer::ppo::Learner;
use host_trainer::rollout::Rollout;
use host_trainer::rollout::collect_rollout;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sitl::env::{OBS_DIM, VecEnv};
use std::path::PathBuf;

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| f64::from(*x) * f64::from(*y))
        .sum()
}

fn main() {
    let mut args = std::env::args().skip(1);
    let run = PathBuf::from(args.next().unwrap_or("runs/stage1_imitation".into()));
    let k: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(6);
    let lambda: Option<f32> = args.next().and_then(|s| s.parse().ok());
    let mut config = TrainConfig::load(&run.join("config.toml")).expect("the run's config.toml");
    let device = burn::tensor::Device::flex().autodiff();
    let (iteration, learner) =
        checkpoint_learner(&config, &run, &device).expect("the run's latest checkpoint");
    if let Some(l) = lambda {
        config.ppo.lambda = l;
    }
    let arch = config.architecture().expect("a row-A config");
    let payload = learner.actor.payload();
    let policy = Policy::from_payload(&arch, &payload).expect("the actor as a blob");
    let std = learner.actor.std();
    let (n, steps) = (config.env.num_envs, config.ppo.steps_per_env);
    println!(
        "{}: checkpoint at iteration {iteration}, σ {:?}, {k} rollouts of {n} envs x {steps} steps (B = {}), γ {}, λ {}",
        run.display(),
        std,
        n * steps,
        config.ppo.gamma,
        config.ppo.lambda
    );
    let mut grads = Vec::new();
    let mut batches = Vec::new();
    for i in 0..k {
        let seed = 1_000 + i as u64;
        let rollout = fresh_rollout(&policy, &std, &config, seed);
        let batch = learner.prepare(&rollout, &config.ppo);
        let mean_ret =
            batch.returns.iter().map(|&r| f64::from(r)).sum::<f64>() / batch.len() as f64;
        let var_ret = batch
            .returns
            .iter()
            .map(|&r| (f64::from(r) - mean_ret).powi(2))
            .sum::<f64>()
            / batch.len() as f64;
        let resid: Vec<f64> = batch
            .returns
            .iter()
            .zip(&batch.old_values)
            .map(|(r, v)| f64::from(r - v))
            .collect();
        let mean_res = resid.iter().sum::<f64>() / resid.len() as f64;
        let var_res =
            resid.iter().map(|r| (r - mean_res).powi(2)).sum::<f64>() / resid.len() as f64;
        let g = learner.actor_gradient(&batch, &config.ppo);
        println!(
            "rollout {i}: |g| {:.4e}, returns mean {mean_ret:.4} sd {:.4}, critic explained variance {:.3}",
            dot(&g, &g).sqrt(),
            var_ret.sqrt(),
            1.0 - var_res / var_ret.max(1e-12)
        );
        grads.push(g);
        batches.push(batch);
    }
    signal_share(&grads, (n * steps) as f64);

    // The PPO direction of all rollouts together, and the reward along it.
    let all = union(&batches);
    let saturated: Vec<String> = (0..4)
        .map(|k| {
            let m = all.old_mean.iter().skip(k).step_by(4);
            let n = all.old_mean.len() / 4;
            let over = m.filter(|v| v.abs() > 0.9).count();
            format!("{:.1}%", 100.0 * over as f64 / n as f64)
        })
        .collect();
    println!("mean actions with |μ| > 0.9 (clipped at 1 by the env), per motor: {saturated:?}");
    let flat = learner.actor_gradient(&all, &config.ppo);
    let rms = (dot(&flat, &flat) / flat.len() as f64).sqrt();
    let base = reward_per_step(&learner.actor.payload(), &arch, &std, &config);
    println!(
        "reward per step along the update direction (common random numbers), unchanged: {base:.6}"
    );
    reward_along_the_update(&learner, &all, &arch, &std, &config, rms, base);

    // Past the peak, does the estimate point back? The gradient at θ stepped by ε towards
    // the update (the same critic), against the direction at θ.
    for eps in [3e-5, 1e-4] {
        let mut stepped = learner.clone_networks();
        let grads = learner.actor_gradients(&all, &config.ppo);
        stepped.actor = SgdConfig::new()
            .init()
            .step(eps / rms, learner.actor.clone(), grads);
        let stepped_payload = stepped.actor.payload();
        let policy = Policy::from_payload(&arch, &stepped_payload).expect("blob");
        let mut cos = Vec::new();
        for i in 0..3 {
            let seed = 2_000 + i as u64;
            let rollout = fresh_rollout(&policy, &std, &config, seed);
            let g = stepped.actor_gradient(&stepped.prepare(&rollout, &config.ppo), &config.ppo);
            cos.push(dot(&g, &flat) / (dot(&g, &g) * dot(&flat, &flat)).sqrt());
        }
        println!(
            "after a step of ε = {eps:.0e} towards the update: cosine of the new gradient with the old direction {:?}",
            cos.iter().map(|c| format!("{c:+.3}")).collect::<Vec<_>>()
        );
    }
}

/// The mean pairwise cosine `c` of the rollouts' gradients `grads`, and what it says of the
/// batch `b` (samples): the signal's share of |g|² and the batch at which signal = noise.
fn signal_share(grads: &[Vec<f32>], b: f64) {
    let k = grads.len();
    let mut cos = Vec::new();
    for i in 0..k {
        for j in i + 1..k {
            let c = dot(&grads[i], &grads[j])
                / (dot(&grads[i], &grads[i]) * dot(&grads[j], &grads[j])).sqrt();
            cos.push(c);
        }
    }
    let c = cos.iter().sum::<f64>() / cos.len().max(1) as f64;
    let sd = (cos.iter().map(|x| (x - c).powi(2)).sum::<f64>() / cos.len().max(1) as f64).sqrt();
    println!(
        "mean pairwise cosine c = {c:.4} (sd {sd:.4} over {} pairs)",
        cos.len()
    );
    if c > 0.0 {
        println!(
            "signal share of |g|² at B = {b:.0}: {c:.4}; batch for signal = noise: {:.3e} samples ({:.0}x)",
            b * (1.0 - c) / c,
            (1.0 - c) / c
        );
    } else {
        println!("no common direction measurable at this batch size");
    }
}

/// The reward per step after SGD steps of several per-weight RMS sizes towards the update
/// `all` gives, against it, and in a random direction, as a Markdown table (`base`: the
/// reward unchanged; `rms`: the gradient's per-weight RMS).
fn reward_along_the_update(
    learner: &Learner,
    all: &Batch,
    arch: &Architecture,
    std: &[f32],
    config: &TrainConfig,
    rms: f64,
    base: f64,
) {
    println!("| per-weight RMS step ε | towards the update | against it | a random direction |");
    println!("|---|---|---|---|");
    let mut noise_rng = ChaCha8Rng::seed_from_u64(99);
    let payload = learner.actor.payload();
    let noise: Vec<f32> = (0..payload.len())
        .map(|_| host_trainer::rng::normal(&mut noise_rng))
        .collect();
    for eps in [1e-5, 3e-5, 1e-4, 3e-4, 1e-3] {
        let mut row = Vec::new();
        for sign in [1.0, -1.0] {
            let lr = sign * eps / rms;
            let grads = learner.actor_gradients(all, &config.ppo);
            let stepped = SgdConfig::new()
                .init()
                .step(lr, learner.actor.clone(), grads);
            let r = reward_per_step(&stepped.payload(), arch, std, config);
            if eps == 1e-4 && sign > 0.0 {
                action_change(&payload, &stepped.payload(), arch, &all.obs);
            }
            row.push(format!("{r:.6} ({:+.1}%)", 100.0 * (r - base) / base.abs()));
        }
        let random: Vec<f32> = payload
            .iter()
            .zip(&noise)
            .map(|(w, z)| w + eps as f32 * z)
            .collect();
        let r = reward_per_step(&random, arch, std, config);
        row.push(format!("{r:.6} ({:+.1}%)", 100.0 * (r - base) / base.abs()));
        println!("| {eps:.0e} | {} | {} | {} |", row[0], row[1], row[2]);
    }
}

/// How the mean action moves between two actors on `obs`: per action dimension, the mean
/// shift and its RMS.
fn action_change(a: &[f32], b: &[f32], arch: &Architecture, obs: &[f32]) {
    let (pa, pb) = (
        Policy::from_payload(arch, a).expect("blob"),
        Policy::from_payload(arch, b).expect("blob"),
    );
    let (Policy::A(na), Policy::A(nb)) = (pa, pb) else {
        return;
    };
    let mut sum = [0.0f64; 4];
    let mut sq = [0.0f64; 4];
    let mut n = 0.0;
    for o in obs.chunks_exact(OBS_DIM).step_by(7) {
        let Ok(o) = <&[f32; OBS_DIM]>::try_from(o) else {
            continue;
        };
        let (ma, mb) = (na.forward(o), nb.forward(o));
        for k in 0..4 {
            let d = f64::from(mb[k] - ma[k]);
            sum[k] += d;
            sq[k] += d * d;
        }
        n += 1.0;
    }
    println!(
        "  mean action shift per motor at ε = 1e-4 towards the update: {:?}, RMS {:?}",
        sum.map(|s| format!("{:+.5}", s / n)),
        sq.map(|s| format!("{:.5}", (s / n).sqrt()))
    );
}

/// A rollout of the run's size from environments seeded with `seed`, after as many steps
/// again to leave the spawn states behind (the update sees envs mid-flight).
fn fresh_rollout(policy: &Policy<'_>, std: &[f32], config: &TrainConfig, seed: u64) -> Rollout {
    let (n, steps) = (config.env.num_envs, config.ppo.steps_per_env);
    let mut env = VecEnv::time_trial(config.env_config(seed));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut rollout = Rollout::new(n, OBS_DIM);
    for _ in 0..2 {
        collect_rollout(
            &mut env,
            policy,
            std,
            steps,
            &mut rng,
            &mut rollout,
            |_, _| {},
        )
        .expect("rollout");
    }
    rollout
}

/// Several batches as one (each keeps the advantage normalisation of its own rollout).
fn union(batches: &[Batch]) -> Batch {
    let mut all = batches[0].clone();
    for b in &batches[1..] {
        all.obs.extend_from_slice(&b.obs);
        all.actions.extend_from_slice(&b.actions);
        all.old_log_prob.extend_from_slice(&b.old_log_prob);
        all.old_mean.extend_from_slice(&b.old_mean);
        all.old_values.extend_from_slice(&b.old_values);
        all.returns.extend_from_slice(&b.returns);
        all.advantages.extend_from_slice(&b.advantages);
    }
    all
}

/// Mean reward per step of the actor `payload` with noise σ `std`, measured as the trainer's
/// `[guard]` measures it (1,024 envs, 50 steps to leave the spawns, then 250 measured), on
/// the same seed every call: common random numbers.
fn reward_per_step(payload: &[f32], arch: &Architecture, std: &[f32], config: &TrainConfig) -> f64 {
    let guard = Guard {
        envs: 1024,
        warmup_steps: 50,
        steps: 250,
    };
    measured_return(payload, std, arch, config, &guard, 777).expect("measured return")
}
