//! `learning-curves`: several training runs on one page, against samples and wall-clock:
//! the referee's success and best lap, the rollout's gates and crashes per second, and the
//! policy's σ. Reads each run's `metrics.jsonl`, from `host-trainer train` or from
//! `tools/train_rslrl.py` (whose keys differ; both are read), and draws the authors' own
//! figure-8 run (RSL-RL on a GPU, no gate in 410 M samples; docs/TRAINING.md) beside them on
//! the paper's scale.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use serde_json::Value;
use sitl::plot::{Series, grid, line_chart};

use crate::error::{Error, Result};

/// The time-optimal lap of the `paper` preset (s): `tools/min_lap_time.py`.
pub const LAP_BOUND_S: f64 = 7.10;

/// Samples of the authors' 500-iteration figure-8 run, which reached no gate (their logs).
pub const AUTHORS_SAMPLES_WITHOUT_A_GATE: f64 = 410e6;

/// What to draw (the arguments of `learning-curves`).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct CurvesArgs {
    /// A run directory holding `metrics.jsonl`, with its legend label after `=` (default:
    /// the directory). Repeat for each run.
    #[arg(long = "run", value_name = "DIR[=LABEL]", required = true, value_parser = run_and_label)]
    pub runs: Vec<(PathBuf, String)>,
    /// The SVG to write.
    #[arg(long, value_name = "FILE", default_value = "learning_curves.svg")]
    pub out: PathBuf,
}

/// `--run DIR[=LABEL]`: the directory and its label (the directory when there is none).
fn run_and_label(value: &str) -> std::result::Result<(PathBuf, String), String> {
    match value.split_once('=') {
        Some((d, l)) if !d.is_empty() && !l.is_empty() => Ok((PathBuf::from(d), l.to_string())),
        Some(_) => Err("expected DIR or DIR=LABEL, neither empty".to_string()),
        None => Ok((PathBuf::from(value), value.to_string())),
    }
}

/// One iteration of a run, whichever trainer wrote it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Point {
    /// Env-steps so far.
    pub samples: f64,
    /// Training wall-clock so far (s), evaluations excluded.
    pub wall_s: f64,
    /// The referee's success rate, where this iteration was evaluated.
    pub referee_success: Option<f64>,
    /// The referee's best lap (s), where evaluated and a lap was flown.
    pub referee_lap_s: Option<f64>,
    /// Gates passed per env and simulated second in the rollout.
    pub gates_per_s: Option<f64>,
    /// Crashes per env and simulated second in the rollout.
    pub crashes_per_s: Option<f64>,
    /// Mean action σ.
    pub sigma: Option<f64>,
    /// The referee's crashes per second, where evaluated.
    pub referee_crashes_per_s: Option<f64>,
    /// Races: the referee's overtakes, where evaluated.
    pub referee_overtakes: Option<f64>,
    /// Races: the referee's sustained overtakes, where evaluated.
    pub referee_sustained: Option<f64>,
    /// Races: the referee's win rate (docs/DESIGN.md "Metrics"), where evaluated.
    pub referee_win_rate: Option<f64>,
    /// The success of `run.select`'s validation (the mean over its perturbations), where
    /// validated.
    pub validation_success: Option<f64>,
}

fn number(v: &Value, keys: &[&str]) -> Option<f64> {
    keys.iter()
        .find_map(|k| v.get(*k).and_then(Value::as_f64))
        .filter(|x| x.is_finite())
}

/// One `metrics.jsonl` line of either trainer: `host-trainer train`'s keys or
/// `tools/train_rslrl.py`'s. `None` when it lacks samples or wall-clock.
pub fn point(v: &Value) -> Option<Point> {
    Some(Point {
        samples: number(v, &["samples"])?,
        wall_s: number(v, &["wall_s"])?,
        referee_success: number(v, &["eval_success_rate", "eval_success"]),
        referee_lap_s: number(v, &["eval_best_lap_s"]),
        gates_per_s: number(v, &["gates_per_s"]),
        crashes_per_s: number(v, &["crash_rate_per_s", "crashes_per_s"]),
        sigma: number(v, &["action_std", "std"]),
        referee_crashes_per_s: number(v, &["eval_crash_rate"]),
        referee_overtakes: number(v, &["eval_overtakes"]),
        referee_sustained: number(v, &["eval_sustained_overtakes"]),
        referee_win_rate: number(v, &["eval_win_rate"]),
        validation_success: number(v, &["select_success_rate"]),
    })
}

/// A run's iterations from its `metrics.jsonl` text (`what` names it in errors). A last line
/// that does not parse is a write cut short by a kill and is skipped; any other is an error.
pub fn parse_metrics(text: &str, what: &str) -> Result<Vec<Point>> {
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    let mut points = Vec::with_capacity(lines.len());
    for (i, line) in lines.iter().enumerate() {
        let parsed = serde_json::from_str::<Value>(line)
            .ok()
            .and_then(|v| point(&v));
        match parsed {
            Some(p) => points.push(p),
            None if i + 1 == lines.len() => {}
            None => {
                return Err(Error::new(format!(
                    "{what} line {}: not a metrics line (needs \"samples\" and \"wall_s\")",
                    i + 1
                )));
            }
        }
    }
    if points.is_empty() {
        return Err(Error::new(format!("{what}: no iterations")));
    }
    Ok(points)
}

fn read_run(dir: &Path) -> Result<Vec<Point>> {
    let path = dir.join("metrics.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|e| {
        Error::new(format!(
            "reading {}: {e} (a run directory of `host-trainer train` or tools/train_rslrl.py)",
            path.display()
        ))
    })?;
    parse_metrics(&text, &path.display().to_string())
}

/// The page of charts for `runs` (label, iterations) as SVG.
pub fn page(runs: &[(String, Vec<Point>)]) -> String {
    let m = 1e-6;
    let series = |f: &dyn Fn(&Point) -> Option<(f64, f64)>| -> Vec<Series> {
        runs.iter()
            .map(|(label, points)| Series {
                name: label.clone(),
                points: points.iter().filter_map(f).collect(),
            })
            .collect()
    };
    let max_samples = runs
        .iter()
        .flat_map(|(_, p)| p.iter().map(|p| p.samples))
        .fold(0.0f64, f64::max);
    let mut laps = series(&|p| p.referee_lap_s.map(|l| (p.samples * m, l)));
    laps.push(Series {
        name: format!("time-optimal bound ({LAP_BOUND_S} s)"),
        points: vec![(0.0, LAP_BOUND_S), (max_samples * m, LAP_BOUND_S)],
    });
    let mut paper_scale = series(&|p| p.referee_success.map(|s| (p.samples * m, s)));
    paper_scale.push(Series {
        name: "the authors' run (RSL-RL, GPU): no gate".into(),
        points: vec![(0.0, 0.0), (AUTHORS_SAMPLES_WITHOUT_A_GATE * m, 0.0)],
    });
    let samples = "samples (M env-steps)";
    let mut charts = vec![
        line_chart(
            "referee success against samples",
            samples,
            "success (gates passed / met)",
            &series(&|p| p.referee_success.map(|s| (p.samples * m, s))),
        ),
        line_chart(
            "referee success against wall-clock",
            "training wall-clock (min)",
            "success (gates passed / met)",
            &series(&|p| p.referee_success.map(|s| (p.wall_s / 60.0, s))),
        ),
        line_chart(
            "referee best lap (where a lap was flown)",
            samples,
            "best lap (s)",
            &laps,
        ),
        line_chart(
            "rollout gates per second (noisy policy)",
            samples,
            "gates / env / s",
            &series(&|p| p.gates_per_s.map(|g| (p.samples * m, g))),
        ),
        line_chart(
            "rollout crashes per second (noisy policy)",
            samples,
            "crashes / env / s",
            &series(&|p| p.crashes_per_s.map(|c| (p.samples * m, c))),
        ),
        line_chart(
            "policy σ (mean over motors)",
            samples,
            "σ (action units)",
            &series(&|p| p.sigma.map(|s| (p.samples * m, s))),
        ),
    ];
    if runs
        .iter()
        .any(|(_, p)| p.iter().any(|p| p.validation_success.is_some()))
    {
        charts.push(line_chart(
            "validation success (run.select: what keep_best ranks by)",
            samples,
            "success (mean over the validation's perturbations)",
            &series(&|p| p.validation_success.map(|s| (p.samples * m, s))),
        ));
    }
    let races = runs
        .iter()
        .any(|(_, p)| p.iter().any(|p| p.referee_overtakes.is_some()));
    if !races {
        // The authors' stage-1 run beside ours (a time trial's scale).
        charts.push(line_chart(
            "referee success on the paper's scale",
            samples,
            "success (gates passed / met)",
            &paper_scale,
        ));
    } else {
        let mut overtakes = series(&|p| p.referee_overtakes.map(|o| (p.samples * m, o)));
        for (s, (label, _)) in overtakes.iter_mut().zip(runs) {
            s.name = format!("{label}: all");
        }
        let mut sustained = series(&|p| p.referee_sustained.map(|o| (p.samples * m, o)));
        for (s, (label, _)) in sustained.iter_mut().zip(runs) {
            s.name = format!("{label}: sustained (lead held 2 s)");
        }
        overtakes.extend(sustained);
        charts.extend([
            line_chart(
                "races: referee overtakes per evaluation",
                samples,
                "overtakes",
                &overtakes,
            ),
            line_chart(
                "races: referee crashes per second",
                samples,
                "crashes / s",
                &series(&|p| p.referee_crashes_per_s.map(|c| (p.samples * m, c))),
            ),
            line_chart(
                "races: referee win rate against samples",
                samples,
                "win rate (flights won + ties / 2)",
                &series(&|p| p.referee_win_rate.map(|w| (p.samples * m, w))),
            ),
            line_chart(
                "races: referee win rate against wall-clock",
                "training wall-clock (min)",
                "win rate (flights won + ties / 2)",
                &series(&|p| p.referee_win_rate.map(|w| (p.wall_s / 60.0, w))),
            ),
        ]);
    }
    grid(&charts, 2)
}

/// Reads the runs and writes the page.
pub fn run(args: &CurvesArgs) -> Result<ExitCode> {
    let runs = args
        .runs
        .iter()
        .map(|(dir, label)| Ok((label.clone(), read_run(dir)?)))
        .collect::<Result<Vec<_>>>()?;
    let svg = page(&runs);
    std::fs::write(&args.out, svg)
        .map_err(|e| Error::new(format!("writing {}: {e}", args.out.display())))?;
    for (label, points) in &runs {
        let last = points.last().copied().unwrap_or_default();
        let best = points
            .iter()
            .filter_map(|p| p.referee_success)
            .fold(None, |b: Option<f64>, s| Some(b.map_or(s, |b| b.max(s))));
        let lap = points
            .iter()
            .filter_map(|p| p.referee_lap_s)
            .fold(None, |b: Option<f64>, l| Some(b.map_or(l, |b| b.min(l))));
        println!(
            "{label}: {} iterations, {:.1} M samples, {:.1} min; best referee success {}, best lap {}",
            points.len(),
            last.samples * 1e-6,
            last.wall_s / 60.0,
            best.map_or("-".into(), |b| format!("{b:.3}")),
            lap.map_or("none".into(), |l| format!("{l:.2} s")),
        );
    }
    println!("wrote {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_trainers_metrics_are_read() {
        let ours = r#"{"iteration":20,"samples":1024000,"wall_s":49.5,"success_rate":0.2,"crash_rate_per_s":0.78,"gates_per_s":0.21,"action_std":0.305,"eval_success_rate":0.5,"eval_crash_rate":0.31,"eval_best_lap_s":9.5}"#;
        let rslrl = r#"{"iteration": 1, "samples": 409600, "wall_s": 16.968, "gates_per_s": 0.02, "crashes_per_s": 1.55, "std": 1.0, "eval_success": 0.0, "eval_best_lap_s": null}"#;
        let p = parse_metrics(&format!("{ours}\n{rslrl}\n"), "m").unwrap();
        assert_eq!(p.len(), 2);
        assert_eq!(p[0].referee_success, Some(0.5));
        assert_eq!(p[0].referee_lap_s, Some(9.5));
        assert_eq!(p[0].crashes_per_s, Some(0.78));
        assert_eq!(p[0].sigma, Some(0.305));
        assert_eq!(p[1].samples, 409600.0);
        assert_eq!(p[1].referee_success, Some(0.0));
        assert_eq!(p[1].referee_lap_s, None);
        assert_eq!(p[1].crashes_per_s, Some(1.55));
        assert_eq!(p[1].sigma, Some(1.0));
    }

    #[test]
    fn a_cut_last_line_is_skipped_and_any_other_bad_line_is_an_error() {
        let good = r#"{"samples":1,"wall_s":1}"#;
        assert_eq!(
            parse_metrics(&format!("{good}\n{{\"samp"), "m")
                .unwrap()
                .len(),
            1
        );
        let e = parse_metrics(&format!("{{\"x\":1}}\n{good}"), "m").unwrap_err();
        assert!(e.to_string().contains("line 1"), "{e}");
        assert!(parse_metrics("", "m").is_err());
    }

    #[test]
    fn the_page_has_every_run_the_bound_and_the_authors_run() {
        let points = parse_metrics(
            r#"{"samples":5e6,"wall_s":60,"eval_success_rate":0.7,"eval_best_lap_s":8.2}"#,
            "m",
        )
        .unwrap();
        let svg = page(&[("seed 1".into(), points)]);
        assert!(svg.starts_with("<svg"), "{}", &svg[..40.min(svg.len())]);
        assert!(svg.contains("seed 1"));
        assert!(svg.contains("time-optimal bound"));
        assert!(svg.contains("no gate"));
        assert!(!svg.contains("win rate"));
    }

    #[test]
    fn a_race_run_gets_the_race_charts_and_not_the_time_trials_scale() {
        let points = parse_metrics(
            r#"{"samples":5e6,"wall_s":60,"eval_success_rate":0.9,"eval_crash_rate":0.05,"eval_overtakes":30,"eval_sustained_overtakes":12,"eval_win_rate":0.62}"#,
            "m",
        )
        .unwrap();
        assert_eq!(points[0].referee_overtakes, Some(30.0));
        assert_eq!(points[0].referee_sustained, Some(12.0));
        assert_eq!(points[0].referee_win_rate, Some(0.62));
        assert_eq!(points[0].referee_crashes_per_s, Some(0.05));
        let svg = page(&[("G".into(), points)]);
        assert!(svg.contains("referee win rate against wall-clock"));
        assert!(svg.contains("G: sustained (lead held 2 s)"));
        assert!(!svg.contains("no gate"));
        assert!(!svg.contains("validation success"));
        // A run ranked by run.select also gets its validation's chart.
        let points = parse_metrics(
            r#"{"samples":5e6,"wall_s":60,"eval_success_rate":0.9,"select_success_rate":0.91}"#,
            "m",
        )
        .unwrap();
        assert_eq!(points[0].validation_success, Some(0.91));
        assert!(page(&[("G".into(), points)]).contains("validation success"));
    }
}
