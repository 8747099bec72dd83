//! The subcommands of `sitl`, one module each, and the arguments they share.
//!
//! | module | subcommand |
//! |---|---|
//! | [`eval`] | `sitl eval`: the Table-1 row over many seeded episodes, in-process |
//! | [`fly`] | `sitl fly`: one time trial with every lap |
//! | [`race`] | `sitl race`: a lockstep race over MAVLink |
//! | [`fc`] | `sitl fc`: one controller as a MAVLink endpoint |
//! | [`int8`] | `sitl int8-check`: what converting a blob to int8 costs |
//! | [`robustness`] | `sitl robustness`: scores under the standard perturbations, f32 and int8 |

pub mod eval;
pub mod fc;
pub mod fly;
pub mod int8;
pub mod race;
pub mod robustness;

use clap::Args;
use sitl::dynamics::Preset;
use sitl::env::PresetName;
use sitl::eval::EvalConfig;
use sitl::perturb::{Perturbation, StartJitter};
use sitl::pilot::PilotSpec;
use sitl::referee::{EPISODE_SECONDS, SpawnMode};
use std::path::{Path, PathBuf};

/// Who races and how they are scored: what `eval`, `race` and `int8-check` share. Each
/// command words `--ego` and `--opponent` for what it does with them (`mut_arg` on its
/// arguments): `eval` and `int8-check` require `--ego`, `race` defaults both to the shipped
/// policies.
#[derive(Args)]
pub struct Contest {
    /// The ego.
    #[arg(long)]
    pub ego: Option<String>,
    /// The opponent; without one the ego flies a time trial.
    #[arg(long)]
    pub opponent: Option<String>,
    #[command(flatten)]
    pub common: Common,
    #[command(flatten)]
    pub scoring: Scoring,
}

impl Contest {
    /// `--ego`, where the command requires it (clap has checked it was given).
    pub fn required_ego(&self) -> Result<&str, String> {
        self.ego
            .as_deref()
            .ok_or_else(|| "--ego is required".to_string())
    }

    /// The ego and the opponent, loaded for the preset; an ego that observes an opponent
    /// must be given one.
    pub fn pilots(&self) -> Result<(PilotSpec, Option<PilotSpec>), String> {
        let preset = self.common.preset;
        let ego_spec = self.required_ego()?;
        let ego = load(ego_spec, &preset, "--ego")?;
        let opponent = load_opponent(self.opponent.as_deref(), &preset)?;
        if opponent.is_none() && ego.needs_opponent() {
            return Err(format!(
                "--ego {ego_spec} observes an opponent; race it with --opponent <blob|baseline>"
            ));
        }
        Ok((ego, opponent))
    }

    /// The episodes to fly: preset and seconds of [`Common`], the rest of [`Scoring`].
    pub fn eval_config(&self) -> EvalConfig {
        EvalConfig {
            preset: self.common.preset,
            episodes: self.scoring.episodes,
            seconds: self.common.seconds,
            seed: self.scoring.seed,
            spawn: self.scoring.spawn,
            perturbation: self.scoring.perturbation(),
        }
    }
}

/// The world every command flies in.
#[derive(Args)]
pub struct Common {
    /// Dynamics preset: paper (half propeller force, as the paper's simulator), nominal or
    /// realistic.
    #[arg(long, default_value = "paper", value_parser = parse_preset)]
    pub preset: Preset,
    /// Simulated seconds per episode.
    #[arg(long, default_value_t = EPISODE_SECONDS, value_parser = parse_seconds)]
    pub seconds: f32,
}

/// The episodes a pilot is scored over, as `sitl eval` and `sitl race` share them.
#[derive(Args)]
pub struct Scoring {
    /// Number of episodes.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub episodes: u32,
    /// Seed of the spawn draws; episode i uses stream i of it.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Where drones start and restart: stage1 (time trials' default), stage2 (races'
    /// default), or along-track.
    #[arg(long, value_parser = clap::value_parser!(SpawnMode))]
    pub spawn: Option<SpawnMode>,
    /// Also write the report as JSON to this file (`sitl race` adds the controllers' links).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also record every episode's positions and overtakes as JSON to this file (for
    /// `cargo run -p tools -- overtake-figure`).
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Jitter every spawn of every drone, per axis: `--jitter` alone for ±5 cm, ±5° and
    /// ±0.2 m/s, or `--jitter pos=M,att-deg=DEG,vel=MPS` (docs/DESIGN.md "Perturbations").
    #[arg(long, value_name = "SPEC", num_args = 0..=1, default_missing_value = "",
          value_parser = parse_jitter)]
    pub jitter: Option<StartJitter>,
    /// Perturb the ego, comma-separated KEY=VALUE, each a value X or a span LO:HI drawn per
    /// episode: thrust, mass, inertia (factors), motor-tau-ms, latency (20 ms steps), noise
    /// (multiple of a Crazyflie's estimate), noise-pos (m), noise-vel (m/s), noise-att-deg,
    /// noise-rate (rad/s). E.g. `--perturb thrust=0.95:1.05,latency=1,noise=1`.
    #[arg(long, value_name = "SPEC", value_parser = parse_perturbation)]
    pub perturb: Option<Perturbation>,
}

impl Scoring {
    /// `--perturb` with `--jitter`'s start jitter.
    pub fn perturbation(&self) -> Perturbation {
        let mut p = self.perturb.unwrap_or(Perturbation::NONE);
        if let Some(j) = self.jitter {
            p.jitter = j;
        }
        p
    }

    /// Writes the recorded episodes to `--trace`, if given.
    pub fn write_traces(
        &self,
        pilots: &[String],
        preset: &Preset,
        episodes: &[sitl::referee::Episode],
    ) -> Result<(), String> {
        let Some(path) = &self.trace else {
            return Ok(());
        };
        let json = serde_json::json!({
            "format": sitl::referee::TRACES_FORMAT,
            "pilots": pilots,
            "preset": preset.name,
            "seed": self.seed,
            "episodes": episodes.iter().map(|e| e.trace.to_json()).collect::<Vec<_>>(),
        });
        write(path, json.to_string().as_bytes())
    }

    /// Writes the recorded episodes to `path` as a 3-D replay ([`sitl::replay`]), the
    /// pilots named by their files' names.
    pub fn write_replay(
        &self,
        path: &Path,
        track: &firmware_core::track::Track<'_>,
        pilots: &[String],
        preset: &Preset,
        episodes: &[sitl::referee::Episode],
    ) -> Result<(), String> {
        let short: Vec<String> = pilots.iter().map(|p| sitl::replay::short_name(p)).collect();
        let title = format!(
            "{} ({} preset, seed {})",
            short.join(" vs "),
            preset.name,
            self.seed
        );
        let info = sitl::replay::ReplayInfo {
            title: &title,
            pilots,
            preset: preset.name,
            seed: self.seed,
        };
        let page = sitl::replay::html(&sitl::replay::replay_json(track, &info, episodes));
        write_quietly(path, page.as_bytes())?;
        eprintln!(
            "wrote {} ({:.1} MB: open it in a browser)",
            path.display(),
            page.len() as f64 / 1e6
        );
        Ok(())
    }
}

/// The pilot `spec` names (a blob or `baseline[...]`), tuned to `preset`; errors name
/// `flag`.
pub fn load(spec: &str, preset: &Preset, flag: &str) -> Result<PilotSpec, String> {
    PilotSpec::load(spec, preset).map_err(|e| format!("{flag}: {e}"))
}

/// The opponent `spec` names, if any (errors name `--opponent`).
pub fn load_opponent(spec: Option<&str>, preset: &Preset) -> Result<Option<PilotSpec>, String> {
    spec.map(|o| load(o, preset, "--opponent")).transpose()
}

/// Writes `bytes` to `path` atomically.
pub fn write_quietly(path: &Path, bytes: &[u8]) -> Result<(), String> {
    sitl::files::write_atomically(path, bytes)
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// Writes `bytes` to `path` atomically and says so on stderr.
pub fn write(path: &Path, bytes: &[u8]) -> Result<(), String> {
    write_quietly(path, bytes)?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

/// `--preset`.
pub fn parse_preset(s: &str) -> Result<Preset, String> {
    s.parse::<PresetName>().map(PresetName::preset)
}

/// `--perturb`.
fn parse_perturbation(s: &str) -> Result<Perturbation, String> {
    Perturbation::NONE.parse_onto(s)
}

/// `--jitter`.
fn parse_jitter(s: &str) -> Result<StartJitter, String> {
    Perturbation::NONE.with_jitter(s).map(|p| p.jitter)
}

/// Seconds of an episode: at least one control step ([`sitl::world::CONTROL_PERIOD_NS`],
/// 0.02 s), at most an hour.
fn parse_seconds(s: &str) -> Result<f32, String> {
    let step_s = sitl::world::CONTROL_PERIOD_NS as f32 * 1e-9;
    match s.parse::<f32>() {
        Ok(v) if v >= step_s && v <= 3600.0 => Ok(v),
        _ => Err(format!(
            "must be a number of seconds in [{step_s}, 3600] (at least one control step)"
        )),
    }
}
