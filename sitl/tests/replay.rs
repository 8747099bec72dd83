//! The 3-D replay (`sitl::replay`): the page gives back every recorded trajectory exactly,
//! holds everything it needs, and no name can break it. That the page draws the drones and
//! gates where they were is checked in a browser by `tools/replay/check.py` (CI).

use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, evaluate};
use sitl::perturb::Perturbation;
use sitl::pilot::PilotSpec;
use sitl::referee::{Episode, Trace, TraceEventKind};
use sitl::replay::{ReplayInfo, html, read, replay_json, short_name, trace};
use sitl::world::World;

const STAGE1: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");

fn fly(opponent: Option<&str>, episodes: u32) -> (World, Vec<Episode>) {
    let preset = Preset::paper();
    let ego = PilotSpec::load(STAGE1, &preset).unwrap();
    let opponent = opponent.map(|o| PilotSpec::load(o, &preset).unwrap());
    let config = EvalConfig {
        preset,
        episodes,
        seconds: 15.0,
        seed: 5,
        spawn: None,
        perturbation: Perturbation::JITTERED,
    };
    let episodes = evaluate(&ego, opponent.as_ref(), &config, true);
    (config.world(opponent.is_some()), episodes)
}

fn page(world: &World, pilots: &[String], episodes: &[Episode]) -> String {
    let info = ReplayInfo {
        title: "a <b>race</b> & more",
        pilots,
        preset: "paper",
        seed: 5,
    };
    html(&replay_json(&world.track, &info, episodes))
}

#[test]
fn a_race_replay_gives_back_every_recorded_value_exactly() {
    let (world, episodes) = fly(Some("baseline:7"), 3);
    let pilots = vec!["stage1".to_string(), "baseline".to_string()];
    let json = read(&page(&world, &pilots, &episodes)).unwrap();
    assert_eq!(json["episodes"].as_array().unwrap().len(), 3);
    for (i, e) in episodes.iter().enumerate() {
        assert!(e.trace.steps() > 0 && !e.trace.opponent_m.is_empty());
        assert_eq!(trace(&json, i).unwrap(), e.trace, "episode {i}");
    }
    // The same values as the trace's JSON (`--trace`), which writes f32 in decimal.
    let t0 = Trace::from_json(&episodes[0].trace.to_json()).unwrap();
    assert_eq!(t0, episodes[0].trace);
}

#[test]
fn a_time_trial_replay_has_no_opponent_and_no_lead() {
    let (world, episodes) = fly(None, 2);
    let json = read(&page(&world, &["stage1".into()], &episodes)).unwrap();
    let e = &json["episodes"][0];
    assert!(e["opponent"].is_null() && e["lead_m"].is_null());
    let back = trace(&json, 0).unwrap();
    assert_eq!(back, episodes[0].trace);
    assert!(back.opponent_m.is_empty() && back.lead_m.is_empty());
}

#[test]
fn the_events_are_the_referees_counts() {
    let (_, episodes) = fly(Some("baseline:7"), 4);
    for e in &episodes {
        let (m, t) = (&e.metrics, &e.trace);
        let count = |drone: u8, crash: bool| {
            t.events
                .iter()
                .filter(|ev| {
                    ev.drone == drone && matches!(ev.kind, TraceEventKind::Crashed { .. }) == crash
                })
                .count() as u32
        };
        assert_eq!(count(0, false), m.gates_passed);
        assert_eq!(count(0, true), m.crashes);
        assert_eq!(count(1, true), m.opponent_crashes);
        assert_eq!(t.overtakes.len() as u32, m.overtakes);
        assert_eq!(t.lead_m.len(), t.steps());
        // Every crash ends the flight: the next step is a respawn, unless the episode ended.
        for ev in t
            .events
            .iter()
            .filter(|ev| matches!(ev.kind, TraceEventKind::Crashed { .. }))
        {
            assert!(
                t.respawns.contains(&ev.step) || ev.step as usize == t.steps(),
                "a crash at step {} without a restart",
                ev.step
            );
        }
    }
    let all: u32 = episodes.iter().map(|e| e.metrics.gates_passed).sum();
    assert!(
        all > 20,
        "the ego passed {all} gates: too few to test the events"
    );
    let crashes: u32 = episodes
        .iter()
        .map(|e| e.metrics.crashes + e.metrics.opponent_crashes)
        .sum();
    assert!(crashes > 0, "no crash: the crash events went untested");
}

#[test]
fn the_page_is_self_contained_and_no_name_can_close_its_data() {
    let (world, episodes) = fly(Some("baseline:7"), 1);
    let pilots = vec!["</script><script>alert(1)</script>".to_string(), "b".into()];
    let page = page(&world, &pilots, &episodes);
    let json = read(&page).unwrap();
    assert_eq!(json["pilots"][0], pilots[0]);
    assert_eq!(
        page.matches("</script>").count(),
        3,
        "data, three.js, viewer"
    );
    assert!(page.contains("<title>a &lt;b>race&lt;/b> &amp; more</title>"));
    for external in ["<script src", "<link", "import(", "fetch("] {
        assert!(
            !page.contains(external),
            "the page loads something: {external}"
        );
    }
}

#[test]
fn a_page_without_replay_data_or_of_another_format_is_refused() {
    assert!(
        read("<html></html>")
            .unwrap_err()
            .contains("no replay data")
    );
    let other = r#"<script type="application/json" id="replay-data">{"format":"x"}</script>"#;
    assert!(read(other).unwrap_err().contains("format"));
    let torn = r#"<script type="application/json" id="replay-data">{"format":"#;
    assert!(read(torn).is_err());
}

#[test]
fn a_trace_written_before_attitudes_and_events_still_reads() {
    let old = serde_json::json!({
        "dt_s": 0.02,
        "ego_m": [[0.0, 1.0, 2.0]],
        "opponent_m": [],
        "respawns": [],
        "overtakes": [],
    });
    let t = Trace::from_json(&old).unwrap();
    assert_eq!(t.steps(), 1);
    assert!(t.ego_attitude.is_empty() && t.events.is_empty() && t.lead_m.is_empty());
}

#[test]
fn a_page_whose_states_do_not_match_its_step_count_is_refused() {
    let (world, episodes) = fly(Some("baseline:7"), 1);
    let page = page(&world, &["a".into(), "b".into()], &episodes);
    let mut json = read(&page).unwrap();
    let steps = json["episodes"][0]["steps"].as_u64().unwrap();
    json["episodes"][0]["steps"] = (steps + 1).into();
    assert!(
        trace(&json, 0)
            .unwrap_err()
            .contains("values, not 8 for each of")
    );
    json["episodes"][0]["steps"] = steps.into();
    json["episodes"][0]["ego"] = serde_json::Value::Null;
    assert!(trace(&json, 0).unwrap_err().contains("no ego states"));
    assert!(trace(&json, 1).unwrap_err().contains("no episode 1"));
}

#[test]
fn pilots_are_named_by_their_files_and_the_baseline_by_itself() {
    assert_eq!(
        short_name("/a/b/stage1.blob (stage1)"),
        "stage1.blob (stage1)"
    );
    assert_eq!(short_name("policies/x.blob"), "x.blob");
    assert_eq!(
        short_name("baseline (7.0 m/s cruise)"),
        "baseline (7.0 m/s cruise)"
    );
}
