//! `sitl eval` and `sitl fly` as a user runs them: the Table-1 row, the JSON keys, and clear
//! errors with a non-zero exit for bad input.

use std::process::Command;

fn sitl(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_sitl"))
        .args(args)
        .output()
        .expect("runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn temp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("sitl-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn eval_prints_the_row_and_writes_every_json_key() {
    let json = temp("race.json");
    let plot = temp("race.svg");
    let (ok, out, err) = sitl(&[
        "eval",
        "--plot",
        plot.to_str().unwrap(),
        "--ego",
        "baseline:8:0.4",
        "--opponent",
        "baseline:6.5",
        "--preset",
        "paper",
        "--episodes",
        "3",
        "--seconds",
        "20",
        "--seed",
        "5",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("| success rate"), "{out}");
    assert!(out.contains("sustained overtakes"), "{out}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    for key in [
        "episodes",
        "sim_seconds",
        "gates_passed",
        "gates_encountered",
        "success_rate",
        "success_rate_ci95",
        "crashes",
        "crash_rate",
        "crash_rate_ci95",
        "best_lap_s",
        "mean_lap_s",
        "laps",
        "overtakes",
        "sustained_overtakes",
        "sustained_overtake_rate",
    ] {
        assert!(v.get(key).is_some(), "missing key {key}");
    }
    assert_eq!(v["episodes"], 3);
    assert_eq!(v["sim_seconds"].as_f64().unwrap().round(), 60.0);
    assert!(v["success_rate_ci95"].is_array());
    let svg = std::fs::read_to_string(&plot).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains(">g5<"), "{svg}");
    assert!(
        svg.matches("<polyline").count() >= 3,
        "centreline, ego, opponent"
    );
}

#[test]
fn a_perturbed_eval_says_so_and_records_it() {
    let json = temp("perturbed.json");
    let (ok, out, err) = sitl(&[
        "eval",
        "--ego",
        "baseline",
        "--episodes",
        "2",
        "--seconds",
        "5",
        "--jitter",
        "--perturb",
        "thrust=0.95:1.05,latency=1,noise=1",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        out.contains("perturbed: jitter 5 cm/5°/0.20 m/s, thrust x0.95-1.05, latency 1 steps"),
        "{out}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let p = &v["perturbation"];
    assert_eq!(p["latency_steps"], serde_json::json!([1, 1]));
    assert!((p["thrust_scale"]["lo"].as_f64().unwrap() - 0.95).abs() < 1e-6);
    assert!((p["jitter"]["position_m"].as_f64().unwrap() - 0.05).abs() < 1e-6);
    assert!((p["sensor_noise"]["velocity_mps"].as_f64().unwrap() - 0.05).abs() < 1e-6);
    // Unperturbed, the JSON has no perturbation key (the shipped eval.json files stay valid).
    let plain = temp("plain.json");
    let (ok, _, err) = sitl(&[
        "eval",
        "--ego",
        "baseline",
        "--episodes",
        "1",
        "--seconds",
        "1",
        "--json",
        plain.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&plain).unwrap()).unwrap();
    assert!(v.get("perturbation").is_none());
}

#[test]
fn a_dnf_and_no_overtake_are_null() {
    let json = temp("dnf.json");
    // 5 s is too short for a lap; alone there is no overtake.
    let (ok, _, err) = sitl(&[
        "eval",
        "--ego",
        "baseline",
        "--episodes",
        "2",
        "--seconds",
        "5",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert!(v["best_lap_s"].is_null());
    assert!(v["mean_lap_s"].is_null());
    assert!(v["sustained_overtake_rate"].is_null());
}

#[test]
fn bad_input_is_a_clear_error() {
    let corrupt = temp("corrupt.blob");
    std::fs::write(&corrupt, b"OVTK\x01\x00\x00\x00 definitely not a blob").unwrap();
    let cases: [(&[&str], &str); 12] = [
        (
            &["eval", "--ego", "/no/such.blob"],
            "cannot read /no/such.blob",
        ),
        (
            &["eval", "--ego", corrupt.to_str().unwrap()],
            "not a usable policy blob",
        ),
        (
            &["eval", "--ego", "baseline", "--preset", "moon"],
            "unknown preset 'moon'",
        ),
        (
            &["eval", "--ego", "baseline", "--episodes", "0"],
            "0 is not in 1..=100000",
        ),
        (
            &["eval", "--ego", "baseline", "--seconds", "0"],
            "number of seconds",
        ),
        (
            &["eval", "--ego", "baseline", "--seconds", "0.01"],
            "at least one control step",
        ),
        (&["eval", "--ego", "baseline:fast"], "cruise speed must be"),
        (&["eval"], "--ego"),
        (
            &["eval", "--ego", "baseline", "--perturb", "mass=-1"],
            "mass: must lie in [0.1, 10]",
        ),
        (
            &["eval", "--ego", "baseline", "--perturb", "noise=nan"],
            "noise: 'nan' is not a finite number",
        ),
        (
            &["eval", "--ego", "baseline", "--perturb", "latency=100"],
            "latency: whole control steps in [0, 50]",
        ),
        (
            &["eval", "--ego", "baseline", "--jitter", "pos=2"],
            "jitter pos (m): must be a number in [0, 1]",
        ),
    ];
    for (args, message) in cases {
        let (ok, _, err) = sitl(args);
        assert!(!ok, "{args:?} succeeded");
        assert!(err.contains(message), "{args:?}: {err}");
    }
}

#[test]
fn a_blob_that_observes_an_opponent_needs_one() {
    let blob = temp("g.blob");
    std::fs::write(
        &blob,
        firmware_core::synthetic::blob(firmware_core::policy::TableRow::G, 3).unwrap(),
    )
    .unwrap();
    let (ok, _, err) = sitl(&["eval", "--ego", blob.to_str().unwrap()]);
    assert!(!ok);
    assert!(err.contains("observes an opponent"), "{err}");
    // With one it flies (random weights crash, but the race is scored).
    let (ok, out, err) = sitl(&[
        "eval",
        "--ego",
        blob.to_str().unwrap(),
        "--opponent",
        "baseline",
        "--episodes",
        "2",
        "--seconds",
        "3",
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("| success rate"));
}

#[test]
fn fly_prints_the_laps() {
    let (ok, out, err) = sitl(&["fly", "--seconds", "30"]);
    assert!(ok, "{err}");
    assert!(out.contains("laps (s)"), "{out}");
    assert!(out.contains("best lap"), "{out}");
}

#[test]
fn race_with_the_shipped_defaults_prints_the_row_and_writes_its_files() {
    let dir = temp("race-default");
    std::fs::create_dir_all(&dir).unwrap();
    let (tlog, plot, json) = (dir.join("r.tlog"), dir.join("r.svg"), dir.join("r.json"));
    let replay = dir.join("r.html");
    let (ok, out, err) = sitl(&[
        "race",
        "--replay",
        replay.to_str().unwrap(),
        "--episodes",
        "2",
        "--seconds",
        "5",
        "--gcs",
        "none",
        "--tlog",
        tlog.to_str().unwrap(),
        "--plot",
        plot.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("| success rate"), "{out}");
    assert!(out.contains("x real time"), "{out}");
    // The shipped opponent: row A learned from a random network.
    assert!(
        err.contains("vs opponent") && err.contains("policies/stage1.blob (stage1)"),
        "the shipped opponent: {err}"
    );
    assert!(std::fs::metadata(&tlog).unwrap().len() > 0);
    assert!(std::fs::read_to_string(&plot).unwrap().starts_with("<svg"));
    assert!(std::fs::metadata(&replay).unwrap().len() > 0);
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    for key in [
        "success_rate",
        "crash_rate",
        "best_lap_s",
        "sustained_overtake_rate",
        "controllers",
        "realtime_factor",
    ] {
        assert!(j.get(key).is_some(), "missing {key}");
    }
}

#[test]
fn race_and_fc_refuse_bad_input_clearly() {
    let (ok, _, err) = sitl(&["race", "--ego", "/no/such.blob", "--episodes", "1"]);
    assert!(
        !ok && err.contains("--ego") && err.contains("/no/such.blob"),
        "{err}"
    );
    let (ok, _, err) = sitl(&["race", "--gcs", "not-an-address", "--episodes", "1"]);
    assert!(!ok && err.contains("--gcs"), "{err}");
    let (ok, _, err) = sitl(&["race", "--signing-key", "", "--episodes", "1"]);
    assert!(!ok && err.contains("signing key"), "{err}");
    let (ok, _, err) = sitl(&["fc", "--blob", "baseline", "--sysid", "0"]);
    assert!(!ok && err.contains("sysid"), "{err}");
}
