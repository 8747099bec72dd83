//! Sweeps the baseline's cruise speed on a preset: gates, crashes and best lap in 45 s.
//! `cargo run --release -p overtake-tests --example baseline_speed_sweep [paper|nominal|realistic]`
use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::track::{CrashRules, Track};
use sitl::dynamics::Preset;
use sitl::referee::{EpisodeConfig, run_episode};
use sitl::world::World;

fn main() {
    let name = std::env::args().nth(1).unwrap_or_else(|| "paper".into());
    let Some(preset) = Preset::by_name(&name) else {
        eprintln!("unknown preset '{name}': paper, nominal or realistic");
        std::process::exit(2);
    };
    let base = sitl::pilot::baseline_config_for(&preset);
    let track = Track::figure_eight();
    let world = World::figure_eight(preset, CrashRules::STAGE1);
    for speed in [4.0f32, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0] {
        let mut pilot = BaselineController::new(
            BaselineConfig {
                cruise_speed_mps: speed,
                ..base
            },
            track,
        );
        let s = run_episode(
            &world,
            &mut pilot,
            None,
            &EpisodeConfig::time_trial(45.0),
            0,
            false,
        )
        .metrics;
        let best = s
            .best_lap_s()
            .map_or("DNF".to_string(), |t| format!("{t:.2} s"));
        println!(
            "{name} cruise {speed:4.1} m/s: {:3} gates, {} crashes, best lap {best}",
            s.gates_passed, s.crashes
        );
    }
}
