//! Where a time-trial policy's mirror images lie: flies a blob deterministically in its
//! run's environment (`--config`, spawns as in training) and, per target gate, measures the
//! mean squared distance between the policy's mean and its mean on the step's mirror image
//! with the motors renumbered back (`sitl::mirror`), with the image's attitude quaternion as
//! `Mirror::state` gives it and with its sign chosen so that w has the sign of the flown
//! state's w. A symmetric policy has distance 0 on the images it was trained on; a large
//! distance means the images are inputs the policy has not learned (docs/journal/stage1.md
//! "The faster half teaches the slower").
//!
//! `cargo run --release -p host-trainer --example mirror_images -- \
//!    --config C --blob B` (run e7's blob and config, removed from
//!    policies/ on 2026-12-05: `git show 0b4e8a4:policies/stage1_rl.blob`)

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::observation::Observation;
use firmware_core::policy::PolicyState;
use host_trainer::config::TrainConfig;

/// Where the attitude quaternion (w, x, y, z) sits in a stage-1 observation.
const QUAT: core::ops::Range<usize> = 3..7;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .cloned()
            .ok_or_else(|| format!("missing {name}"))
    };
    let config = TrainConfig::load(std::path::Path::new(&arg("--config")?))?;
    let raw = std::fs::read(arg("--blob")?)?;
    let bytes = sitl::env::interned(&AlignedBytes::new(&raw));
    let blob = Blob::parse(bytes.as_bytes()).map_err(|e| format!("{e:?}"))?;
    let policy = blob.policy().map_err(|e| format!("{e:?}"))?;
    let mut env = config.make_env(7)?;
    let mirror = env.mirror()?.clone();
    let (n, dim) = (env.num_envs(), env.obs_dim());
    let gates = 6;
    // Per target gate: [sum as given, sum sign-matched, samples, images with w of the
    // other sign than the flown state's, the two sums on commands clipped to [-1, 1],
    // sum of the mean's mean |component|].
    let mut acc = vec![[0.0f64; 7]; gates];
    let mut images = Vec::new();
    let mut actions = vec![0.0f32; n * 4];
    let act = |o: &[f32]| {
        Observation::from_values(o).and_then(|o| policy.act(&o, &mut PolicyState::Stateless))
    };
    for _ in 0..500 {
        env.mirrored_observations(&mut images)?;
        let obs = env.observations().to_vec();
        let targets: Vec<usize> = env.target_gates().collect();
        for e in 0..n {
            let o = &obs[e * dim..(e + 1) * dim];
            let mut img = images[e * dim..(e + 1) * dim].to_vec();
            let (Some(mean), Some(given)) = (act(o), act(&img)) else {
                continue;
            };
            actions[e * 4..e * 4 + 4].copy_from_slice(&mean);
            let flipped = img[QUAT.start] * o[QUAT.start] < 0.0;
            if flipped {
                img[QUAT].iter_mut().for_each(|v| *v = -*v);
            }
            let Some(matched) = act(&img) else { continue };
            let sq = |m: [f32; 4], clip: bool| {
                let t = mirror.motors(&m);
                let c = |v: f32| if clip { v.clamp(-1.0, 1.0) } else { v };
                (0..4)
                    .map(|k| f64::from(c(mean[k]) - c(t[k])).powi(2))
                    .sum::<f64>()
            };
            let a = &mut acc[targets[e] % gates];
            a[0] += sq(given, false);
            a[1] += sq(matched, false);
            a[2] += 1.0;
            a[3] += f64::from(u8::from(flipped));
            a[4] += sq(given, true);
            a[5] += sq(matched, true);
            a[6] += mean.iter().map(|m| f64::from(m.abs())).sum::<f64>() / 4.0;
        }
        env.step(&actions)?;
    }
    println!(
        "target gate | samples | images with the other sign of w | mean |μ| | distance as given | sign-matched | clipped commands: as given | sign-matched"
    );
    for (g, a) in acc.iter().enumerate() {
        let c = a[2].max(1.0);
        println!(
            "g{g} | {} | {:.2} | {:.2} | {:.3} | {:.3} | {:.3} | {:.3}",
            a[2],
            a[3] / c,
            a[6] / c,
            a[0] / c,
            a[1] / c,
            a[4] / c,
            a[5] / c
        );
    }
    Ok(())
}
