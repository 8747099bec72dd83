//! The Python module `overtake._overtake`: a thin layer over [`sitl::env::VecEnv`] and
//! firmware-core's blob policies. The Gymnasium `VectorEnv` around it is Python
//! (`python/overtake/__init__.py`); this layer only converts arguments, releases the GIL
//! for the steps, and turns every Rust error into a Python exception with its message.
//!
//! Arrays cross the boundary as numpy arrays: float32 observations, actions and rewards,
//! bool episode ends, float64 reward terms (as the environment sums them). Actions must be
//! float32 `[num_envs, 4]` (any strides); each call returns fresh arrays, so a learner may
//! keep the ones it was given.

mod policy;

use firmware_core::blob::AlignedBytes;
use firmware_core::nn::ACTION_DIM;
use firmware_core::policy::TableRow;
use numpy::ndarray::{Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayDescrMethods, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use sitl::env::{Competition, EnvConfig, EnvError, RaceConfig, RewardWeights, Task, VecEnv};

/// The bytes of the blob at `path` (at most `sitl::env::MAX_BLOB_BYTES`), or `OSError`
/// (`FileNotFoundError` when it is missing) naming the path.
fn read_blob(what: &str, path: &std::path::Path) -> PyResult<AlignedBytes> {
    sitl::env::read_blob(path).map_err(|e| {
        let message = format!("{what} '{}': {}", path.display(), {
            match &e {
                EnvError::ReadOpponent { message, .. } => message.clone(),
                other => other.to_string(),
            }
        });
        match e {
            EnvError::ReadOpponent {
                kind: std::io::ErrorKind::NotFound,
                ..
            } => PyFileNotFoundError::new_err(message),
            _ => PyOSError::new_err(message),
        }
    })
}

/// Refuses `arr` unless it is a float32 array whose shape matches `shape` (`None`: any
/// length on that axis): `TypeError` for the type, `ValueError` for the shape.
fn expect_f32(arr: &Bound<'_, PyAny>, what: &str, shape: &[Option<usize>]) -> PyResult<()> {
    let Ok(a) = arr.cast::<PyUntypedArray>() else {
        return Err(PyTypeError::new_err(format!(
            "{what}: expected a numpy float32 array, got {}",
            arr.get_type().name()?
        )));
    };
    let dtype = a.dtype();
    if !dtype.is_equiv_to(&numpy::dtype::<f32>(arr.py())) {
        return Err(PyTypeError::new_err(format!(
            "{what}: expected dtype float32, got {dtype}"
        )));
    }
    let ok = a.ndim() == shape.len()
        && a.shape()
            .iter()
            .zip(shape)
            .all(|(got, want)| want.is_none_or(|w| w == *got));
    if !ok {
        let want: Vec<String> = shape
            .iter()
            .map(|d| d.map_or("n".to_string(), |d| d.to_string()))
            .collect();
        return Err(PyValueError::new_err(format!(
            "{what}: expected shape ({}), got {:?}",
            want.join(", "),
            a.shape()
        )));
    }
    Ok(())
}

/// The values of `a` in row-major order: one copy of the memory when `a` is C-contiguous,
/// else element by element in logical order. (numpy's own `as_slice` also accepts a
/// Fortran-ordered array, whose memory is column-major: rows would be mixed up.)
fn row_major(a: numpy::ndarray::ArrayView2<'_, f32>) -> Vec<f32> {
    match a.as_slice() {
        Some(s) => s.to_vec(),
        None => a.iter().copied().collect(),
    }
}

/// A batch of stage-1 (time trial) or stage-2 (race) environments, auto-resetting.
#[pyclass(module = "overtake._overtake")]
struct RustVecEnv {
    env: VecEnv,
    config: EnvConfig,
}

/// The paper's reward weights with the named ones replaced (`progress`, `command`,
/// `smoothness`, `pass`, `crash`; each finite and >= 0).
fn reward_weights_from(
    overrides: std::collections::HashMap<String, f32>,
) -> PyResult<RewardWeights> {
    let mut w = RewardWeights::default();
    let mut names: Vec<_> = overrides.into_iter().collect();
    names.sort_by(|a, b| a.0.cmp(&b.0));
    for (name, value) in names {
        let slot = match name.as_str() {
            "progress" => &mut w.progress,
            "command" => &mut w.command,
            "smoothness" => &mut w.smoothness,
            "pass" => &mut w.pass,
            "crash" => &mut w.crash,
            _ => {
                return Err(PyValueError::new_err(format!(
                    "reward_weights: unknown term '{name}' (the terms are progress, command, smoothness, pass and crash)"
                )));
            }
        };
        // Its range is checked with the rest by `EnvConfig::validate` ("reward.NAME: ...").
        *slot = value;
    }
    Ok(w)
}

fn bools<'py>(py: Python<'py>, v: impl Iterator<Item = bool>) -> Bound<'py, PyArray1<bool>> {
    v.collect::<Vec<bool>>().into_pyarray(py)
}

impl RustVecEnv {
    fn build(config: EnvConfig) -> PyResult<VecEnv> {
        VecEnv::new(config).map_err(|e| match &e {
            EnvError::ReadOpponent {
                kind: std::io::ErrorKind::NotFound,
                ..
            } => PyFileNotFoundError::new_err(e.to_string()),
            EnvError::ReadOpponent { .. } => PyOSError::new_err(e.to_string()),
            _ => PyValueError::new_err(e.to_string()),
        })
    }

    /// `actions` as a contiguous `num_envs × 4` vector, or the exception.
    fn actions(&self, actions: &Bound<'_, PyAny>) -> PyResult<Vec<f32>> {
        expect_f32(
            actions,
            "actions",
            &[Some(self.env.num_envs()), Some(ACTION_DIM)],
        )?;
        let a: PyReadonlyArray2<'_, f32> = actions.extract()?;
        Ok(row_major(a.as_array()))
    }

    fn observations<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (n, d) = (self.env.num_envs(), self.env.obs_dim());
        Array2::from_shape_vec((n, d), self.env.observations().to_vec())
            .map(|a| a.into_pyarray(py))
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }
}

#[pymethods]
impl RustVecEnv {
    /// Builds the environments: every argument is required (the defaults live in
    /// `overtake.make_vec_env`) and lands in `sitl::env::EnvConfig`, whose `validate` names
    /// the field that is out of range.
    #[new]
    #[pyo3(signature = (*, task, num_envs, preset, seed, spawn, episode_s,
        random_initial_episode_length, opponent, competition, competition_weight, row,
        velocity_scale_mps, spawn_speed_mps, stage1_fraction, replay_fraction=0.0,
        reward_weights=None, stage2_fraction=0.0, fold_mirror=false, randomize=None,
        randomize_share=1.0, spawn_jitter=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        task: &str,
        num_envs: i64,
        preset: &str,
        seed: u64,
        spawn: &str,
        episode_s: f32,
        random_initial_episode_length: bool,
        opponent: Option<std::path::PathBuf>,
        competition: &str,
        competition_weight: f32,
        row: Option<char>,
        velocity_scale_mps: f32,
        spawn_speed_mps: f32,
        stage1_fraction: f32,
        replay_fraction: f32,
        reward_weights: Option<std::collections::HashMap<String, f32>>,
        stage2_fraction: f32,
        fold_mirror: bool,
        randomize: Option<&str>,
        randomize_share: f32,
        spawn_jitter: Option<&str>,
    ) -> PyResult<Self> {
        let value_error = |e: String| PyValueError::new_err(e);
        let task: Task = task.parse().map_err(value_error)?;
        let row = match row {
            None if task == Task::Race => TableRow::G,
            None => TableRow::A,
            Some(c) => TableRow::from_letter(c).ok_or_else(|| {
                PyValueError::new_err(format!("row '{c}': Table 1 has rows A to G"))
            })?,
        };
        let race = match (task, opponent) {
            (Task::Race, Some(path)) => Some(RaceConfig {
                opponent: path,
                competition: Competition::by_name(competition).ok_or_else(|| {
                    PyValueError::new_err(format!(
                        "competition '{competition}': expected 'dense', 'sparse' or 'lead'"
                    ))
                })?,
                competition_weight,
                // The paper's spawn; training configs may swap the places (`race.ego_ahead_fraction`).
                ego_ahead_fraction: 0.0,
            }),
            (Task::Race, None) => {
                return Err(PyValueError::new_err(
                    "a race needs an opponent: the path of a time-trial blob",
                ));
            }
            (Task::TimeTrial, Some(_)) => {
                return Err(PyValueError::new_err(
                    "a time trial has no opponent: pass task='race'",
                ));
            }
            (Task::TimeTrial, None) => None,
        };
        let config = EnvConfig {
            // An absurd count is refused by `validate` (it names the bound), not cast.
            num_envs: usize::try_from(num_envs).unwrap_or(0),
            preset: preset.parse().map_err(value_error)?,
            spawn: spawn.parse().map_err(value_error)?,
            episode_s,
            random_initial_episode_length,
            velocity_scale_mps,
            spawn_speed_mps,
            stage1_fraction,
            stage2_fraction,
            replay_fraction,
            fold_mirror,
            randomize: randomize
                .map(|r| {
                    sitl::perturb::PerturbSpec::parse(r)
                        .map_err(|e| PyValueError::new_err(format!("randomize: {e}")))
                })
                .transpose()?,
            randomize_share,
            spawn_jitter: spawn_jitter
                .map(|j| {
                    sitl::perturb::JitterSpec::parse(j)
                        .map_err(|e| PyValueError::new_err(format!("spawn_jitter: {e}")))
                })
                .transpose()?,
            layout: row.observation_layout(),
            reward: reward_weights_from(reward_weights.unwrap_or_default())?,
            race,
            seed,
        };
        if let Err(e) = config.validate() {
            return Err(match e.field {
                "num_envs" => PyValueError::new_err(format!("num_envs {num_envs}: {}", e.problem)),
                "layout" => PyValueError::new_err(format!("row {}: {}", row.letter(), e.problem)),
                _ => PyValueError::new_err(e.to_string()),
            });
        }
        Ok(Self {
            env: Self::build(config.clone())?,
            config,
        })
    }

    /// Raises `ValueError` when `policy` observes otherwise than these envs (another
    /// layout, velocity scale or fold: flown here it would see observations it was not
    /// trained on), naming every difference.
    fn check_policy(&self, policy: &policy::Policy) -> PyResult<()> {
        self.config
            .check_policy(&policy.spec)
            .map_err(|e| PyValueError::new_err(e.problem))
    }

    /// The environment's `[env]` settings as JSON (host-trainer's `[env]` table, the keys
    /// of `overtake.env_defaults`).
    #[getter]
    fn env_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.config).map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// Number of envs.
    #[getter]
    fn num_envs(&self) -> usize {
        self.env.num_envs()
    }

    /// Values per observation.
    #[getter]
    fn obs_dim(&self) -> usize {
        self.env.obs_dim()
    }

    /// Simulated seconds per step.
    #[getter]
    fn dt_s(&self) -> f32 {
        self.env.dt_s()
    }

    /// Steps per episode before a time-out.
    #[getter]
    fn max_episode_steps(&self) -> u32 {
        self.env.max_episode_steps()
    }

    /// Steps each env's current episode has run (int64 `[num_envs]`); an episode times
    /// out when its count reaches `max_episode_steps`.
    #[getter]
    fn episode_steps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        self.env
            .episode_steps()
            .into_iter()
            .map(i64::from)
            .collect::<Vec<_>>()
            .into_pyarray(py)
    }

    /// Sets the step counts of the current episodes (one integer >= 0 per env), as RSL-RL's
    /// `init_at_random_ep_len` does; nothing else changes. `ValueError` for a wrong length
    /// or a negative count, and nothing changes then.
    #[setter]
    fn set_episode_steps(&mut self, steps: Vec<i64>) -> PyResult<()> {
        let steps: Vec<u32> = steps
            .iter()
            .map(|&s| {
                u32::try_from(s).map_err(|_| {
                    PyValueError::new_err(format!(
                        "episode step count {s}: expected an integer from 0 to {}",
                        u32::MAX
                    ))
                })
            })
            .collect::<PyResult<_>>()?;
        self.env
            .set_episode_steps(&steps)
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// What happened since the last call, summed over envs, and reset: `steps`,
    /// `gates_passed`, `crashes`, `timeouts`, `opponent_crashes`, `nonfinite_actions` (int)
    /// and each reward term's sum (float, the names of `reward_terms`). Cheap: for a
    /// learner's logs without `step_info` every step.
    fn take_stats<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = self.env.take_stats();
        let d = PyDict::new(py);
        d.set_item("steps", s.steps)?;
        d.set_item("gates_passed", s.gates_passed)?;
        d.set_item("crashes", s.crashes)?;
        d.set_item("timeouts", s.timeouts)?;
        d.set_item("opponent_crashes", s.opponent_crashes)?;
        d.set_item("nonfinite_actions", s.nonfinite_actions)?;
        let t = &s.terms;
        for (name, v) in [
            ("progress", t.progress),
            ("command", t.command),
            ("smoothness", t.smoothness),
            ("pass", t.pass),
            ("crash", t.crash),
            ("competition", t.competition),
        ] {
            d.set_item(name, v)?;
        }
        Ok(d)
    }

    /// The reward's weights now, by term name (`progress`, `command`, `smoothness`,
    /// `pass`, `crash`).
    fn reward_weights<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let w = self.env.reward_weights();
        let d = PyDict::new(py);
        for (name, v) in [
            ("progress", w.progress),
            ("command", w.command),
            ("smoothness", w.smoothness),
            ("pass", w.pass),
            ("crash", w.crash),
        ] {
            d.set_item(name, v)?;
        }
        Ok(d)
    }

    /// Replaces the reward's weights from the next step on: the paper's, with the named
    /// ones replaced (as the constructor's `reward_weights`; a schedule such as
    /// host-trainer's `[pass_decay]` calls it between rollouts). A `reset(seed=...)` keeps
    /// them. `ValueError` for an unknown term or a weight that is not finite and >= 0, and
    /// nothing changes then.
    fn set_reward_weights(
        &mut self,
        reward_weights: std::collections::HashMap<String, f32>,
    ) -> PyResult<()> {
        let config = EnvConfig {
            reward: reward_weights_from(reward_weights)?,
            ..self.config.clone()
        };
        config
            .validate()
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        self.env.set_reward_weights(config.reward);
        self.config = config;
        Ok(())
    }

    /// Restarts: with a seed, the environments are rebuilt as if constructed with it (the
    /// same spawns and initial episode lengths); without, every env starts a new episode
    /// drawn from its own generator. Returns the observations, float32 `[num_envs, obs_dim]`.
    #[pyo3(signature = (seed=None))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seed: Option<u64>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        match seed {
            Some(seed) => {
                self.config.seed = seed;
                let config = self.config.clone();
                self.env = py.detach(|| Self::build(config))?;
            }
            None => py.detach(|| self.env.respawn_all()),
        }
        self.observations(py)
    }

    /// One step of every env with `actions` (float32 `[num_envs, 4]`; clipped to [−1, 1],
    /// a non-finite value becomes 0). Returns (observations, rewards, terminated,
    /// truncated): a crash terminates, a time-out (or in a race the opponent's crash alone)
    /// truncates, and either way the env has already restarted.
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: &Bound<'py, PyAny>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray1<f32>>,
        Bound<'py, PyArray1<bool>>,
        Bound<'py, PyArray1<bool>>,
    )> {
        let actions = self.actions(actions)?;
        py.detach(|| self.env.step(&actions))
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let env = &self.env;
        Ok((
            self.observations(py)?,
            env.rewards().to_vec().into_pyarray(py),
            bools(
                py,
                env.dones()
                    .iter()
                    .zip(env.timeouts())
                    .map(|(d, t)| *d && !t),
            ),
            bools(py, env.timeouts().iter().copied()),
        ))
    }

    /// The last step of every env apart, as a dict: `reward_terms` (float64
    /// `[num_envs, 6]`, the columns `progress`, `command`, `smoothness`, `pass`, `crash`,
    /// `competition`, each × dt and signed; a row's sum is the reward before its cast to
    /// float32), the events (bool `[num_envs]`: `gate_passed`, `crashed`, `timed_out`,
    /// `opponent_crashed`), and the envs that were done with the observation of the state
    /// each episode ended in, before the restart (`final_index` int64 `[k]`, `final_rows`
    /// float32 `[k, obs_dim]`).
    fn step_info<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let r = self.env.records();
        let (n, od) = (self.env.num_envs(), self.env.obs_dim());
        let shape_err = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
        let terms: Vec<f64> = r
            .iter()
            .flat_map(|x| {
                let t = &x.terms;
                [
                    t.progress,
                    t.command,
                    t.smoothness,
                    t.pass,
                    t.crash,
                    t.competition,
                ]
            })
            .collect();
        let d = PyDict::new(py);
        d.set_item(
            "reward_terms",
            Array2::from_shape_vec((n, 6), terms)
                .map_err(shape_err)?
                .into_pyarray(py),
        )?;
        d.set_item("gate_passed", bools(py, r.iter().map(|x| x.gate_passed)))?;
        d.set_item("crashed", bools(py, r.iter().map(|x| x.crashed)))?;
        d.set_item("timed_out", bools(py, r.iter().map(|x| x.timed_out)))?;
        d.set_item(
            "opponent_crashed",
            bools(py, r.iter().map(|x| x.opponent_crashed)),
        )?;
        let ended: Vec<usize> = (0..n).filter(|&i| self.env.dones()[i]).collect();
        let fin = self.env.final_observations();
        let rows: Vec<f32> = ended
            .iter()
            .flat_map(|&i| fin[i * od..(i + 1) * od].iter().copied())
            .collect();
        d.set_item(
            "final_rows",
            Array2::from_shape_vec((ended.len(), od), rows)
                .map_err(shape_err)?
                .into_pyarray(py),
        )?;
        let index: Vec<i64> = ended.iter().map(|&i| i as i64).collect();
        d.set_item("final_index", index.into_pyarray(py))?;
        Ok(d)
    }

    /// Steps `T` times in one Rust loop, without Python in between: `actions` float32
    /// `[T, num_envs, 4]`, contiguous. Returns (observations `[T, n, obs_dim]`, rewards
    /// `[T, n]`, dones `[T, n]`, timeouts `[T, n]`), straight from `VecEnv`'s accessors:
    /// the reference the Python-stepped environment is tested against.
    #[allow(clippy::type_complexity)]
    fn rollout<'py>(
        &mut self,
        py: Python<'py>,
        actions: &Bound<'py, PyAny>,
    ) -> PyResult<(
        Bound<'py, numpy::PyArray3<f32>>,
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray2<bool>>,
        Bound<'py, PyArray2<bool>>,
    )> {
        let (n, od) = (self.env.num_envs(), self.env.obs_dim());
        expect_f32(actions, "actions", &[None, Some(n), Some(ACTION_DIM)])?;
        let a: PyReadonlyArray3<'_, f32> = actions.extract()?;
        let a = a.as_array();
        let a = a
            .as_slice()
            .ok_or_else(|| PyValueError::new_err("actions: expected a C-contiguous array"))?;
        let t = a.len() / (n * ACTION_DIM);
        let env = &mut self.env;
        let (obs, rew, done, timeout) = py
            .detach(|| {
                let (mut obs, mut rew, mut done, mut timeout) = (vec![], vec![], vec![], vec![]);
                for step in a.chunks_exact(n * ACTION_DIM) {
                    env.step(step).map_err(|e| e.to_string())?;
                    obs.extend_from_slice(env.observations());
                    rew.extend_from_slice(env.rewards());
                    done.extend_from_slice(env.dones());
                    timeout.extend_from_slice(env.timeouts());
                }
                Ok::<_, String>((obs, rew, done, timeout))
            })
            .map_err(PyValueError::new_err)?;
        let shape_err = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
        Ok((
            Array3::from_shape_vec((t, n, od), obs)
                .map_err(shape_err)?
                .into_pyarray(py),
            Array2::from_shape_vec((t, n), rew)
                .map_err(shape_err)?
                .into_pyarray(py),
            Array2::from_shape_vec((t, n), done)
                .map_err(shape_err)?
                .into_pyarray(py),
            Array2::from_shape_vec((t, n), timeout)
                .map_err(shape_err)?
                .into_pyarray(py),
        ))
    }
}

/// The shipped pipeline's environment for `task` as JSON: `{"env": [env] table, "reward":
/// weights, "competition", "competition_weight"}`, `sitl::env::EnvConfig::stage1` for a
/// time trial (host-trainer/configs/stage1.toml) and `EnvConfig::stage2` for a race: the
/// defaults of `overtake.make_vec_env`.
#[pyfunction]
fn shipped_env_json(task: &str) -> PyResult<String> {
    let task: Task = task.parse().map_err(PyValueError::new_err)?;
    let config = match task {
        Task::TimeTrial => EnvConfig::stage1(1),
        Task::Race => EnvConfig::stage2(1, ""),
    };
    let (competition, weight) = config.race.as_ref().map_or((Competition::Dense, 0.5), |r| {
        (r.competition, r.competition_weight)
    });
    let json = serde_json::json!({
        "env": config,
        "reward": config.reward,
        "competition": competition,
        "competition_weight": weight,
    });
    Ok(json.to_string())
}

/// The compiled part of the `overtake` package.
#[pymodule]
fn _overtake(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(shipped_env_json, m)?)?;
    m.add_class::<RustVecEnv>()?;
    m.add_class::<policy::Policy>()?;
    m.add("ACTION_DIM", ACTION_DIM)?;
    Ok(())
}
