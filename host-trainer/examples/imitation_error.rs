//! How far a stage-2 student's actions are from its stage-1 teacher's on the student's own
//! flight, by time since the spawn: the measurement that showed the recurrent students
//! drifting past the length of their DAgger rounds (docs/journal/stage2.md, "Why the row-G
//! student fell short of its teacher: its horizon").
//!
//! usage: cargo run --release -p host-trainer --example imitation_error -- \
//!            CONFIG.toml STUDENT.blob [STEPS] [EPISODE_S]
//!
//! Flies the config's race environment (its envs, spawn and opponent) for STEPS control steps
//! (default 1000) with the student's mean, its recurrent state carried and cleared at every
//! respawn, and prints the mean squared difference to the teacher (`warm_start.teacher_blob`)
//! per 50-step bin of steps since the spawn. EPISODE_S overrides `env.episode_s` (the
//! referee's races are 45 s).

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::nn::ACTION_DIM;
use firmware_core::observation::Observation;
use host_trainer::config::TrainConfig;
use std::path::Path;

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [config, student, rest @ ..] = args.as_slice() else {
        return Err("usage: imitation_error CONFIG.toml STUDENT.blob [STEPS] [EPISODE_S]".into());
    };
    let number = |i: usize, default: f64| -> Result<f64, String> {
        rest.get(i)
            .map_or(Ok(default), |s| s.parse().map_err(|e| format!("{s}: {e}")))
    };
    let steps = number(0, 1000.0)? as usize;
    let mut config = TrainConfig::load(Path::new(config)).map_err(|e| e.to_string())?;
    config.env.episode_s = number(1, f64::from(config.env.episode_s))? as f32;
    let teacher_path = config
        .warm_start
        .as_ref()
        .and_then(|w| w.teacher_blob.clone())
        .ok_or("the config has no warm_start.teacher_blob")?;
    let read = |p: &str| -> Result<AlignedBytes, String> {
        Ok(AlignedBytes::new(
            &std::fs::read(p).map_err(|e| format!("{p}: {e}"))?,
        ))
    };
    let (teacher_bytes, student_bytes) = (read(&teacher_path)?, read(student)?);
    let teacher_blob = Blob::parse(teacher_bytes.as_bytes()).map_err(|e| e.to_string())?;
    let student_blob = Blob::parse(student_bytes.as_bytes()).map_err(|e| e.to_string())?;
    let teacher = teacher_blob.policy().map_err(|e| e.to_string())?;
    let policy = student_blob.policy().map_err(|e| e.to_string())?;
    let spec = teacher_blob.header().observation;

    let mut env = config.make_env(7).map_err(|e| e.to_string())?;
    let (n, dim) = (env.num_envs(), env.obs_dim());
    let (mut labels, mut actions) = (vec![0.0f32; n * ACTION_DIM], vec![0.0f32; n * ACTION_DIM]);
    let mut memory = vec![policy.initial_state(); n];
    let mut since_spawn = vec![0usize; n];
    let mut bins: Vec<(f64, usize)> = Vec::new();
    env.respawn_all();
    for _ in 0..steps {
        env.policy_actions(&teacher, &spec, &mut labels);
        let obs = env.observations();
        for e in 0..n {
            let o =
                Observation::from_values(&obs[e * dim..(e + 1) * dim]).ok_or("observation size")?;
            let a = policy
                .act(&o, &mut memory[e])
                .ok_or("the student does not fit the observation")?;
            let bin = since_spawn[e] / 50;
            if bins.len() <= bin {
                bins.resize(bin + 1, (0.0, 0));
            }
            for k in 0..ACTION_DIM {
                actions[e * ACTION_DIM + k] = a[k];
                bins[bin].0 += f64::from(a[k] - labels[e * ACTION_DIM + k]).powi(2);
            }
            bins[bin].1 += ACTION_DIM;
        }
        env.step(&actions).map_err(|e| e.to_string())?;
        for e in 0..n {
            since_spawn[e] += 1;
            if env.dones()[e] {
                memory[e].clear();
                since_spawn[e] = 0;
            }
        }
    }
    let stats = env.take_stats();
    let sim_s = (steps * n) as f64 * f64::from(env.dt_s());
    println!(
        "{student} against {teacher_path}: {:.3} gates/s, {:.3} crashes/s over {steps} steps x {n} envs",
        stats.gates_passed as f64 / sim_s,
        stats.crashes as f64 / sim_s
    );
    println!("| steps since spawn | samples | mse to the teacher |");
    println!("|---|---|---|");
    for (i, (sum, count)) in bins.iter().enumerate().filter(|(_, b)| b.1 > 0) {
        println!(
            "| {}-{} | {} | {:.5} |",
            i * 50,
            i * 50 + 49,
            count / ACTION_DIM,
            sum / *count as f64
        );
    }
    Ok(())
}
