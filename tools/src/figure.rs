//! `overtake-figure`: the paper's Fig. 3 from a recorded race. Reads the episodes that
//! `sitl race --trace` or `sitl eval --opponent … --trace` recorded, picks an overtake (the
//! first sustained one unless told which), and draws the ego's and the opponent's paths
//! over a window around it from above, with the gates, the centreline, each second marked
//! on both paths and the overtake ringed.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use sitl::referee::{TRACES_FORMAT, Trace};

use crate::error::{Error, Result};

/// What to draw (the arguments of `overtake-figure`).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct FigureArgs {
    /// The recorded episodes: the JSON file of `sitl race --trace FILE` or
    /// `sitl eval --opponent ... --trace FILE`.
    #[arg(long, value_name = "FILE")]
    pub trace: PathBuf,
    /// The episode (0-based index); default: the first with a sustained overtake, else the
    /// first with any.
    #[arg(long, value_name = "N")]
    pub episode: Option<usize>,
    /// Which of the episode's overtakes (0-based index); default: its first sustained one.
    #[arg(long, value_name = "K")]
    pub overtake: Option<usize>,
    /// Seconds of flight shown, centred on the overtake, in (0, 60] (the paper's Fig. 3
    /// shows 4 and 8).
    #[arg(long, value_name = "SECONDS", default_value_t = 8.0, value_parser = window_seconds)]
    pub window_s: f32,
    /// The SVG to write.
    #[arg(long, value_name = "FILE", default_value = "overtake.svg")]
    pub out: PathBuf,
    /// Also print a Markdown table of every sustained overtake in the file, per gate: how
    /// many were wide in and tight out, and the mean speeds and line offsets at entry, pass
    /// and exit (`tools::manoeuvre`).
    #[arg(long)]
    pub summary: bool,
}

/// `--window-s`: seconds in (0, 60].
fn window_seconds(value: &str) -> std::result::Result<f32, String> {
    match value.parse::<f32>() {
        Ok(v) if v > 0.0 && v <= 60.0 => Ok(v),
        _ => Err("expected seconds in (0, 60]".to_string()),
    }
}

/// The recorded episodes of a trace file, with the pilots' names.
pub fn read(path: &Path) -> Result<(Vec<String>, Vec<Trace>)> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| Error::new(format!("reading {}: {e}", path.display())))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::new(format!("{}: not JSON: {e}", path.display())))?;
    if v.get("format").and_then(|f| f.as_str()) != Some(TRACES_FORMAT) {
        return Err(Error::new(format!(
            "{}: not a recorded race (format \"{TRACES_FORMAT}\"); write one with `sitl race --trace FILE`",
            path.display()
        )));
    }
    let pilots = v
        .get("pilots")
        .and_then(|p| p.as_array())
        .map(|p| {
            p.iter()
                .filter_map(|s| s.as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default();
    let episodes = v
        .get("episodes")
        .and_then(|e| e.as_array())
        .ok_or_else(|| Error::new(format!("{}: no episodes", path.display())))?
        .iter()
        .enumerate()
        .map(|(i, e)| {
            Trace::from_json(e)
                .ok_or_else(|| Error::new(format!("{}: episode {i} is malformed", path.display())))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((pilots, episodes))
}

/// The (episode, overtake) to draw.
pub fn pick(
    episodes: &[Trace],
    episode: Option<usize>,
    overtake: Option<usize>,
) -> Result<(usize, usize)> {
    let first_sustained = |t: &Trace| t.overtakes.iter().position(|m| m.sustained);
    let e = match episode {
        Some(e) => {
            if e >= episodes.len() {
                return Err(Error::new(format!(
                    "--episode {e}: the file holds {} episodes",
                    episodes.len()
                )));
            }
            e
        }
        None => episodes
            .iter()
            .position(|t| first_sustained(t).is_some())
            .or_else(|| episodes.iter().position(|t| !t.overtakes.is_empty()))
            .ok_or_else(|| {
                Error::new(
                    "no episode has an overtake: nothing to draw (the race ranked as \"Fail\")",
                )
            })?,
    };
    let t = &episodes[e];
    let k = match overtake {
        Some(k) if k < t.overtakes.len() => k,
        Some(k) => {
            return Err(Error::new(format!(
                "--overtake {k}: episode {e} has {} overtakes",
                t.overtakes.len()
            )));
        }
        None => first_sustained(t)
            .or(if t.overtakes.is_empty() {
                None
            } else {
                Some(0)
            })
            .ok_or_else(|| Error::new(format!("episode {e} has no overtake")))?,
    };
    Ok((e, k))
}

/// Draws the figure (see the module doc).
pub fn run(args: &FigureArgs) -> Result<ExitCode> {
    let (pilots, episodes) = read(&args.trace)?;
    let (e, k) = pick(&episodes, args.episode, args.overtake)?;
    let trace = &episodes[e];
    let mark = trace.overtakes[k];
    let steps = trace.ego_m.len();
    let half = ((args.window_s / 2.0) / trace.dt_s.max(1e-3)).round() as usize;
    let centre = mark.step as usize;
    let window = centre.saturating_sub(half)..(centre + half).min(steps);
    let t = |s: usize| s as f32 * trace.dt_s;
    // A blob is named by its provenance name ("path (name)" → "name").
    let short = |p: &String| match (p.find(".blob ("), p.ends_with(')')) {
        (Some(i), true) => p[i + 7..p.len() - 1].to_string(),
        _ => p.clone(),
    };
    let names: Vec<String> = pilots.iter().map(short).collect();
    let title = format!(
        "{}: {} overtake, episode {e}, {:.1}-{:.1} s",
        names.join(" vs "),
        if mark.sustained { "sustained" } else { "an" },
        t(window.start),
        t(window.end)
    );
    let track = firmware_core::track::Track::figure_eight();
    let svg = sitl::plot::top_down_window(&track, trace, window, false, &title);
    sitl::files::write_atomically(&args.out, svg.as_bytes())
        .map_err(|e| Error::new(format!("writing {}: {e}", args.out.display())))?;
    println!(
        "wrote {}: episode {e}, overtake {k} at {:.2} s ({}), {:.0} s window",
        args.out.display(),
        t(centre),
        if mark.sustained {
            "sustained"
        } else {
            "not sustained"
        },
        args.window_s
    );
    let line = crate::manoeuvre::Line::new(&track);
    if let Some(m) = crate::manoeuvre::measure(&line, trace, k) {
        println!("the pass: {}", crate::manoeuvre::describe(&m));
    }
    if args.summary {
        let all = crate::manoeuvre::measure_all(&line, &episodes);
        println!(
            "\n{} overtakes measured, {} sustained; sustained ones per gate ({} s before and after the pass):\n{}",
            all.len(),
            all.iter().filter(|m| m.sustained).count(),
            crate::manoeuvre::LOOK_S,
            crate::manoeuvre::summary(&all)
        );
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sitl::referee::OvertakeMark;

    fn trace(overtakes: &[(u32, bool)]) -> Trace {
        Trace {
            dt_s: 0.02,
            overtakes: overtakes
                .iter()
                .map(|&(step, sustained)| OvertakeMark { step, sustained })
                .collect(),
            ..Trace::default()
        }
    }

    #[test]
    fn the_first_sustained_overtake_is_drawn_unless_told() {
        let eps = [
            trace(&[]),
            trace(&[(100, false)]),
            trace(&[(50, false), (300, true)]),
        ];
        assert_eq!(pick(&eps, None, None).unwrap(), (2, 1));
        assert_eq!(pick(&eps, Some(1), None).unwrap(), (1, 0));
        assert_eq!(pick(&eps, Some(2), Some(0)).unwrap(), (2, 0));
        assert!(pick(&eps, Some(0), None).is_err());
        assert!(pick(&eps, Some(9), None).is_err());
        assert!(pick(&eps, Some(2), Some(5)).is_err());
        let none = [trace(&[])];
        let e = pick(&none, None, None).unwrap_err().to_string();
        assert!(e.contains("no episode has an overtake"), "{e}");
    }

    #[test]
    fn a_file_that_is_not_a_recorded_race_is_refused() {
        let dir = std::env::temp_dir().join(format!("overtake-fig-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("x.json");
        std::fs::write(&p, r#"{"format": "something else"}"#).unwrap();
        assert!(
            read(&p)
                .unwrap_err()
                .to_string()
                .contains("sitl race --trace")
        );
        std::fs::write(&p, "not json").unwrap();
        assert!(read(&p).unwrap_err().to_string().contains("not JSON"));
        let t = trace(&[(10, true)]);
        let doc = serde_json::json!({
            "format": TRACES_FORMAT, "pilots": ["a", "b"], "episodes": [t.to_json()]
        });
        std::fs::write(&p, doc.to_string()).unwrap();
        let (pilots, eps) = read(&p).unwrap();
        assert_eq!((pilots.len(), eps[0].clone()), (2, t));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
