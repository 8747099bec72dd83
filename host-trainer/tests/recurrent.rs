//! The recurrent networks on burn against firmware-core, the code a flight controller runs:
//! a blob exported from a burn LSTM actor gives the same actions step by step (max |Δ| ≤
//! 1e-5, the bound of the feed-forward parity test) for rows E, F and G, from a stored
//! non-zero state, across an episode end in the middle of the window (the controller's
//! reset, i.e. RSL-RL's split-at-dones), and the payload round-trips bit for bit.

use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::observation::Observation;
use firmware_core::policy::{Architecture, Policy, PolicyState, TableRow};
use host_trainer::model::{init_rng, values};
use host_trainer::recurrent::{LstmState, RecurrentActor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The flat state (per layer h, c) of a firmware-core recurrent state.
fn flat(state: &PolicyState) -> Vec<f32> {
    match state {
        PolicyState::Stateless => Vec::new(),
        PolicyState::Lstm1(s) => [s.first.h.as_slice(), &s.first.c].concat(),
        PolicyState::Lstm2(s) => {
            [s.first.h.as_slice(), &s.first.c, &s.deep[0].h, &s.deep[0].c].concat()
        }
    }
}

fn observation(values: &[f32]) -> Observation {
    Observation::from_values(values).unwrap()
}

fn max_diff_over_a_window(row: TableRow) -> f32 {
    let device = Device::flex();
    let arch = Architecture::table1(row);
    let actor = RecurrentActor::new(&arch, 0.5, &mut init_rng(7), &device);
    let payload = actor.net.payload();
    assert_eq!(payload.len(), arch.param_count());
    let back = RecurrentActor::from_payload(&arch, &payload, &actor.std(), &device).unwrap();
    assert_eq!(back.net.payload(), payload, "payload round trip");
    let policy = Policy::from_payload(&arch, &payload).unwrap();

    let (envs, warmup, steps, obs_dim) = (3usize, 10usize, 40usize, 30usize);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0)).collect() };
    // Firmware-core: a warm-up to reach a non-zero state, then the window; env 1's episode
    // ends after window step 19 (its controller resets before step 20).
    let mut states: Vec<PolicyState> = (0..envs).map(|_| policy.initial_state()).collect();
    for s in &mut states {
        for o in draw(warmup * obs_dim).chunks_exact(obs_dim) {
            policy.act(&observation(o), s).unwrap();
        }
    }
    let h0: Vec<f32> = states.iter().flat_map(flat).collect();
    let obs = draw(steps * envs * obs_dim); // time-major [t][env][obs]
    let mut keep = vec![1.0f32; steps * envs];
    keep[20 * envs + 1] = 0.0;
    let mut fw = Vec::new();
    for t in 0..steps {
        for (e, s) in states.iter_mut().enumerate() {
            if keep[t * envs + e] == 0.0 {
                s.clear();
            }
            let o = &obs[(t * envs + e) * obs_dim..(t * envs + e + 1) * obs_dim];
            fw.extend(policy.act(&observation(o), s).unwrap());
        }
    }

    let layers = usize::from(arch.lstm_layers);
    let state = LstmState::from_flat(&h0, layers, 128, &device);
    assert_eq!(state.to_flat(), h0, "flat state round trip");
    let obs_t = Tensor::<3>::from_data(TensorData::new(obs, [steps, envs, obs_dim]), &device);
    let keep_t = Tensor::<2>::from_data(TensorData::new(keep, [steps, envs]), &device);
    let (mean, after) = actor.net.sequence(obs_t, keep_t, state);
    let burn = values(mean);
    assert_eq!(burn.len(), fw.len());
    let end: Vec<f32> = states.iter().flat_map(flat).collect();
    let state_diff = after
        .to_flat()
        .iter()
        .zip(&end)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(state_diff <= 1e-5, "final state: max |Δ| = {state_diff:e}");
    burn.iter()
        .zip(&fw)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max)
}

#[test]
fn burn_lstm_actors_act_as_firmware_core_over_a_window() {
    for row in [TableRow::E, TableRow::F, TableRow::G] {
        let d = max_diff_over_a_window(row);
        println!("row {}: max |Δ| = {d:e}", row.letter());
        assert!(d <= 1e-5, "row {}: max |Δ| = {d:e}", row.letter());
    }
}
