//! `overtake._overtake.Policy`: a flash blob's Gaussian means for batches of observations,
//! through firmware-core (the code the flight controller runs), in parallel over rows.

use crate::{expect_f32, read_blob, row_major};
use firmware_core::blob::Blob;
use firmware_core::nn::ACTION_DIM;
use firmware_core::observation::{Observation, ObservationSpec};
use firmware_core::policy::PolicyState;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rayon::prelude::*;

/// Rows per rayon task in [`Policy::act`].
const POLICY_CHUNK: usize = 16;

/// A flash blob's policy: its Gaussian means for batches of observations, with one
/// recurrent state per row for an LSTM policy.
#[pyclass(module = "overtake._overtake")]
pub(crate) struct Policy {
    policy: firmware_core::policy::Policy<'static>,
    pub(crate) spec: ObservationSpec,
    control_period_ns: u32,
    /// One state per row of the batches given to `act` (empty until the first).
    states: Vec<PolicyState>,
}

#[pymethods]
impl Policy {
    /// Loads the blob at `path` (validated by firmware-core: `OSError` when it cannot be
    /// read, `ValueError` when it is not a valid blob). Its bytes stay in memory for the
    /// rest of the process, one copy per distinct blob.
    #[new]
    fn new(path: std::path::PathBuf) -> PyResult<Self> {
        let bytes = sitl::env::interned(&read_blob("policy", &path)?);
        let invalid = |e: firmware_core::blob::BlobError| {
            PyValueError::new_err(format!("policy '{}': {e}", path.display()))
        };
        let blob = Blob::parse(bytes.as_bytes()).map_err(invalid)?;
        let policy = blob.policy().map_err(invalid)?;
        Ok(Self {
            policy,
            spec: blob.header().observation,
            control_period_ns: blob.header().control_period_ns,
            states: Vec::new(),
        })
    }

    /// Values per observation (17, 20 or 30).
    #[getter]
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }

    /// True for an LSTM policy (rows E-G).
    #[getter]
    fn recurrent(&self) -> bool {
        self.policy.is_recurrent()
    }

    /// The control period the policy was trained at (ns).
    #[getter]
    fn control_period_ns(&self) -> u32 {
        self.control_period_ns
    }

    /// The own-velocity scale of the observations it was trained on (m/s; pass it to
    /// `make_vec_env(velocity_scale_mps=...)`).
    #[getter]
    fn velocity_scale_mps(&self) -> f32 {
        self.spec.velocity_scale_mps
    }

    /// True when it was trained on observations folded by the track's mirror (pass it to
    /// `make_vec_env(fold_mirror=...)`); `act` takes such observations as they are, the
    /// flight controller folds and unfolds around it.
    #[getter]
    fn fold_mirror(&self) -> bool {
        self.spec.is_folded()
    }

    /// The Gaussian means (unclipped), float32 `[n, 4]`, for `obs` float32 `[n, obs_dim]`;
    /// an LSTM policy advances row i's state. A recurrent policy keeps the batch size it
    /// first saw until `reset()`.
    fn act<'py>(
        &mut self,
        py: Python<'py>,
        obs: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        expect_f32(obs, "obs", &[None, Some(self.policy.obs_dim())])?;
        let o: PyReadonlyArray2<'_, f32> = obs.extract()?;
        let o = row_major(o.as_array());
        let dim = self.policy.obs_dim();
        let n = o.len() / dim;
        if self.states.len() != n {
            if self.policy.is_recurrent() && !self.states.is_empty() {
                return Err(PyValueError::new_err(format!(
                    "obs: {n} rows, but the policy holds recurrent states for {}; call reset() to start over",
                    self.states.len()
                )));
            }
            self.states = vec![self.policy.initial_state(); n];
        }
        let policy = &self.policy;
        let states = &mut self.states;
        let mut out = vec![0.0f32; n * ACTION_DIM];
        py.detach(|| {
            out.par_chunks_mut(POLICY_CHUNK * ACTION_DIM)
                .zip(o.par_chunks(POLICY_CHUNK * dim))
                .zip(states.par_chunks_mut(POLICY_CHUNK))
                .for_each(|((out, o), states)| {
                    for ((a, o), s) in out
                        .chunks_exact_mut(ACTION_DIM)
                        .zip(o.chunks_exact(dim))
                        .zip(states)
                    {
                        let mean = Observation::from_values(o).and_then(|o| policy.act(&o, s));
                        a.copy_from_slice(&mean.unwrap_or([f32::NAN; ACTION_DIM]));
                    }
                });
        });
        Array2::from_shape_vec((n, ACTION_DIM), out)
            .map(|a| a.into_pyarray(py))
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// Zeroes the recurrent state of the rows `indices` (all rows, and forgets the batch
    /// size, when `None`).
    #[pyo3(signature = (indices=None))]
    fn reset(&mut self, indices: Option<Vec<i64>>) -> PyResult<()> {
        let Some(indices) = indices else {
            self.states.clear();
            return Ok(());
        };
        let n = self.states.len();
        for i in indices {
            let k = usize::try_from(i).ok().filter(|k| *k < n).ok_or_else(|| {
                PyValueError::new_err(format!("reset: row {i} out of range (0..{n})"))
            })?;
            if let Some(s) = self.states.get_mut(k) {
                s.clear();
            }
        }
        Ok(())
    }
}
