//! The paper's own stack, RSL-RL, as safetensors: export an actor with RSL-RL's parameter
//! names, and import an RSL-RL actor into a blob, so a policy trained with Genesis + rsl_rl
//! can be flown here.
//!
//! Names (RSL-RL `ActorCritic` / `ActorCriticRecurrent`): the LSTM is
//! `memory_a.rnn.{weight_ih,weight_hh,bias_ih,bias_hh}_l{n}` (PyTorch `nn.LSTM`, gates
//! i, f, g, o), the MLP is the `nn.Sequential` `actor` whose linear layers sit at indices
//! 0, 2, 4, … (`actor.{2k}.weight` `[out, in]`, `actor.{2k}.bias`), the action noise is `std`
//! (or `log_std`). A blob keeps `bias_ih + bias_hh`; the export writes that sum as `bias_ih`
//! and zeros as `bias_hh`, which computes the same cell. Critic tensors (`critic.*`,
//! `memory_c.*`) are ignored by the import.

use firmware_core::policy::{Architecture, TensorKind, TensorShape};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;

/// Why an RSL-RL file could not be used.
#[derive(Debug, PartialEq)]
pub enum RslRlError {
    /// Not a safetensors file.
    Format(String),
    /// A tensor the architecture needs is absent.
    Missing(String),
    /// A tensor has another shape than the architecture's.
    Shape {
        /// The tensor.
        name: String,
        /// The shape the architecture needs.
        expected: Vec<usize>,
        /// The shape in the file.
        found: Vec<usize>,
    },
    /// A tensor is not float32.
    Dtype {
        /// The tensor.
        name: String,
        /// Its dtype.
        found: String,
    },
    /// The weights given to the export do not match the architecture.
    WeightCount {
        /// Values the architecture has.
        expected: usize,
        /// Values given.
        got: usize,
    },
}

impl core::fmt::Display for RslRlError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Format(e) => write!(f, "not a safetensors file: {e}"),
            Self::Missing(n) => write!(f, "tensor '{n}' is missing (RSL-RL actor names expected)"),
            Self::Shape {
                name,
                expected,
                found,
            } => write!(
                f,
                "tensor '{name}' has shape {found:?}, the architecture needs {expected:?}"
            ),
            Self::Dtype { name, found } => {
                write!(f, "tensor '{name}' is {found}, only F32 is read")
            }
            Self::WeightCount { expected, got } => {
                write!(
                    f,
                    "expected {expected} weights for the architecture, got {got}"
                )
            }
        }
    }
}

impl std::error::Error for RslRlError {}

/// RSL-RL's name of an actor tensor (for the LSTM bias: the `bias_ih` half).
pub fn actor_name(kind: TensorKind) -> String {
    match kind {
        TensorKind::LstmWeightIh(l) => format!("memory_a.rnn.weight_ih_l{l}"),
        TensorKind::LstmWeightHh(l) => format!("memory_a.rnn.weight_hh_l{l}"),
        TensorKind::LstmBias(l) => format!("memory_a.rnn.bias_ih_l{l}"),
        TensorKind::LinearWeight(k) => format!("actor.{}.weight", 2 * k),
        TensorKind::LinearBias(k) => format!("actor.{}.bias", 2 * k),
    }
}

fn shape_of(t: &TensorShape) -> Vec<usize> {
    if t.cols == 0 {
        vec![t.rows]
    } else {
        vec![t.rows, t.cols]
    }
}

fn le_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// The actor of `arch` with `weights` (blob payload order) as a safetensors file with
/// RSL-RL's names, plus `std` when given (the policy's action noise).
pub fn export_actor(
    arch: &Architecture,
    weights: &[f32],
    std: Option<&[f32]>,
) -> Result<Vec<u8>, RslRlError> {
    let expected = arch.param_count();
    if weights.len() != expected {
        return Err(RslRlError::WeightCount {
            expected,
            got: weights.len(),
        });
    }
    let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    let mut offset = 0;
    for t in arch.tensors() {
        let values = weights.get(offset..offset + t.len()).unwrap_or(&[]);
        offset += t.len();
        tensors.push((actor_name(t.kind), shape_of(&t), le_bytes(values)));
        if let TensorKind::LstmBias(l) = t.kind {
            tensors.push((
                format!("memory_a.rnn.bias_hh_l{l}"),
                vec![t.rows],
                le_bytes(&vec![0.0; t.rows]),
            ));
        }
    }
    if let Some(s) = std {
        tensors.push(("std".into(), vec![s.len()], le_bytes(s)));
    }
    let views: Vec<(String, TensorView<'_>)> = tensors
        .iter()
        .map(|(n, shape, data)| {
            TensorView::new(Dtype::F32, shape.clone(), data)
                .map(|v| (n.clone(), v))
                .map_err(|e| RslRlError::Format(e.to_string()))
        })
        .collect::<Result<_, _>>()?;
    let mut meta = HashMap::new();
    meta.insert(
        "format".to_string(),
        "rsl_rl actor (overtake export)".to_string(),
    );
    safetensors::tensor::serialize(views, Some(meta)).map_err(|e| RslRlError::Format(e.to_string()))
}

/// The actor weights of `arch` (blob payload order) from an RSL-RL safetensors file: tensors
/// by RSL-RL name (a common prefix such as `model_state_dict.` is allowed), LSTM biases
/// summed, critic tensors ignored.
pub fn import_actor(bytes: &[u8], arch: &Architecture) -> Result<Vec<f32>, RslRlError> {
    let st = SafeTensors::deserialize(bytes).map_err(|e| RslRlError::Format(e.to_string()))?;
    let names: Vec<String> = st.names().into_iter().map(String::from).collect();
    let read = |name: &str, shape: &[usize]| -> Result<Vec<f32>, RslRlError> {
        let key = names
            .iter()
            .find(|n| n.as_str() == name)
            .or_else(|| {
                let mut m = names.iter().filter(|n| n.ends_with(&format!(".{name}")));
                match (m.next(), m.next()) {
                    (Some(one), None) => Some(one),
                    _ => None,
                }
            })
            .ok_or_else(|| RslRlError::Missing(name.to_string()))?;
        let view = st
            .tensor(key)
            .map_err(|e| RslRlError::Format(e.to_string()))?;
        if view.dtype() != Dtype::F32 {
            return Err(RslRlError::Dtype {
                name: key.clone(),
                found: format!("{:?}", view.dtype()),
            });
        }
        if view.shape() != shape {
            return Err(RslRlError::Shape {
                name: key.clone(),
                expected: shape.to_vec(),
                found: view.shape().to_vec(),
            });
        }
        Ok(view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    };
    let mut out = Vec::with_capacity(arch.param_count());
    for t in arch.tensors() {
        let shape = shape_of(&t);
        match t.kind {
            TensorKind::LstmBias(l) => {
                let ih = read(&format!("memory_a.rnn.bias_ih_l{l}"), &shape)?;
                let hh = read(&format!("memory_a.rnn.bias_hh_l{l}"), &shape)?;
                out.extend(ih.iter().zip(&hh).map(|(a, b)| a + b));
            }
            kind => out.extend(read(&actor_name(kind), &shape)?),
        }
    }
    Ok(out)
}
