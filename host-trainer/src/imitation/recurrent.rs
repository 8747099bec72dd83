//! The recurrent regression of a warm start (rows E-G): the student run over windows of
//! `ppo.steps_per_env` steps with backpropagation through each window, from states the
//! current student recomputes at every epoch.

use super::{Regression, Round, actor_holding};
use crate::config::WarmStart;
use crate::error::TrainError;
use crate::grads::{transfer_gradients, weighted_sum};
use crate::model::values;
use crate::recurrent::{LstmState, RecurrentActor};
use burn::module::Module;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::nn::ACTION_DIM;
use firmware_core::policy::Architecture;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

/// A minibatch of the recurrent regression: the windows of `envs` in round `round` from
/// step `t0` for `len` steps, starting from the states `starts[start]`.
struct Window {
    round: usize,
    t0: usize,
    len: usize,
    start: usize,
    envs: Vec<usize>,
}

/// The recurrent regression of one warm-start stage.
pub(super) struct RecurrentFit<'a> {
    pub(super) arch: &'a Architecture,
    pub(super) warm: &'a WarmStart,
    pub(super) device: &'a Device,
    pub(super) n: usize,
    pub(super) obs_dim: usize,
    /// Steps per window (backpropagation through time).
    pub(super) window: usize,
    pub(super) optim: ModuleOptimizer,
    /// The rounds kept, oldest first.
    pub(super) data: Vec<Round>,
}

impl Regression<RecurrentActor> for RecurrentFit<'_> {
    fn keep(&mut self, flown: Round) -> usize {
        self.data.push(flown);
        let per_round = self.n * self.warm.steps_per_env;
        let keep_rounds = (self.warm.max_samples / per_round.max(1)).max(1);
        if self.data.len() > keep_rounds {
            self.data.drain(..self.data.len() - keep_rounds);
        }
        self.data.len() * per_round
    }

    fn epoch(
        &mut self,
        actor: RecurrentActor,
        round: u32,
        rng: &mut ChaCha8Rng,
    ) -> Result<(RecurrentActor, f64), TrainError> {
        let data = std::mem::take(&mut self.data);
        let result = self.fit_epoch(actor, &data, round, rng);
        self.data = data;
        result
    }
}

impl RecurrentFit<'_> {
    /// One pass over `data` in DAgger round `round`: the windows' starting states from the
    /// current student, then every window minibatch in a random order. Returns the student
    /// and the epoch's mean squared error.
    fn fit_epoch(
        &mut self,
        mut actor: RecurrentActor,
        data: &[Round],
        round: u32,
        rng: &mut ChaCha8Rng,
    ) -> Result<(RecurrentActor, f64), TrainError> {
        let (windows, starts) = self.windows(&actor, data, rng)?;
        let (mut sum, mut count) = (0.0, 0.0);
        for w in &windows {
            let (a, value) = self.step(actor, &data[w.round], w, &starts[w.start], round)?;
            actor = a;
            sum += value;
            count += 1.0;
        }
        Ok((actor, sum / f64::max(count, 1.0)))
    }

    /// The (round, window start, envs) minibatches of `data`, shuffled, with the states the
    /// windows start from (the current student run from zero at each round's start).
    fn windows(
        &self,
        actor: &RecurrentActor,
        data: &[Round],
        rng: &mut ChaCha8Rng,
    ) -> Result<(Vec<Window>, Vec<Vec<f32>>), TrainError> {
        let (n, obs_dim, window) = (self.n, self.obs_dim, self.window);
        let envs_per_batch = (self.warm.minibatch / window).clamp(1, n);
        let valid = self.device.clone().without_autodiff();
        let mut batches = Vec::new();
        let mut starts: Vec<Vec<f32>> = Vec::new();
        let start_net = actor.net.valid();
        for (ri, r) in data.iter().enumerate() {
            let steps = r.labels.len() / (n * ACTION_DIM);
            let net = start_net.clone();
            let mut state = net.zero_state(n, &valid);
            for t0 in (0..steps).step_by(window) {
                let len = window.min(steps - t0);
                starts.push(state.to_flat());
                let obs = Tensor::<2>::from_data(
                    TensorData::new(
                        r.obs[t0 * n * obs_dim..(t0 + len) * n * obs_dim].to_vec(),
                        [len * n, obs_dim],
                    ),
                    &valid,
                )
                .reshape([len, n, obs_dim]);
                let keep = Tensor::<2>::from_data(
                    TensorData::new(r.keep[t0 * n..(t0 + len) * n].to_vec(), [len, n]),
                    &valid,
                );
                state = net.sequence(obs, keep, state).1;
                let mut envs: Vec<usize> = (0..n).collect();
                envs.shuffle(rng);
                for group in envs.chunks(envs_per_batch) {
                    batches.push(Window {
                        round: ri,
                        t0,
                        len,
                        start: starts.len() - 1,
                        envs: group.to_vec(),
                    });
                }
            }
        }
        batches.shuffle(rng);
        Ok((batches, starts))
    }

    /// The mean squared error of `actor` over the windows of `envs` in `w` and its gradient.
    fn pass(
        &self,
        actor: &RecurrentActor,
        r: &Round,
        w: &Window,
        envs: &[usize],
        start: &[f32],
    ) -> (GradientsParams, f64) {
        let (n, obs_dim, device) = (self.n, self.obs_dim, self.device);
        let (t0, len, b) = (w.t0, w.len, envs.len());
        let width = LstmState::width(actor.net.lstm.len(), actor.net.hidden());
        let (mut o, mut a, mut k, mut h0) = (
            Vec::with_capacity(len * b * obs_dim),
            Vec::with_capacity(len * b * ACTION_DIM),
            Vec::with_capacity(len * b),
            Vec::with_capacity(b * width),
        );
        for t in t0..t0 + len {
            for &e in envs {
                let i = t * n + e;
                o.extend_from_slice(&r.obs[i * obs_dim..(i + 1) * obs_dim]);
                a.extend_from_slice(&r.labels[i * ACTION_DIM..(i + 1) * ACTION_DIM]);
                k.push(r.keep[i]);
            }
        }
        for &e in envs {
            h0.extend_from_slice(&start[e * width..(e + 1) * width]);
        }
        let obs = Tensor::<2>::from_data(TensorData::new(o, [len * b, obs_dim]), device)
            .reshape([len, b, obs_dim]);
        let keep = Tensor::<2>::from_data(TensorData::new(k, [len, b]), device);
        let act = Tensor::<2>::from_data(TensorData::new(a, [len * b, ACTION_DIM]), device);
        let state = LstmState::from_flat(&h0, actor.net.lstm.len(), actor.net.hidden(), device);
        let (mean, _) = actor.net.sequence(obs, keep, state);
        let loss = (mean - act).square().mean();
        let value = f64::from(values(loss.clone().inner()).first().copied().unwrap_or(0.0));
        (GradientsParams::from_grads(loss.backward(), actor), value)
    }

    /// One Adam step of `actor` on window minibatch `w` of round data `r`.
    ///
    /// The two halves of the minibatch run on the two cores: the mean over the whole
    /// minibatch is the size-weighted mean of the halves' means, and so is its gradient. The
    /// second half runs on a copy of the actor with parameters of its own (burn's autodiff
    /// cannot run two backward passes through shared parameters at once); its gradients are
    /// moved onto the actor's.
    fn step(
        &mut self,
        actor: RecurrentActor,
        r: &Round,
        w: &Window,
        start: &[f32],
        round: u32,
    ) -> Result<(RecurrentActor, f64), TrainError> {
        let (arch, warm, device) = (self.arch, self.warm, self.device);
        let (left, right) = w.envs.split_at(w.envs.len() / 2);
        let (grads, value) = if left.is_empty() {
            self.pass(&actor, r, w, right, start)
        } else {
            let twin = actor_holding(&actor, arch, &actor.net.payload(), device)?;
            let this = &*self;
            let ((gl, vl), (gr, vr)) = std::thread::scope(|sc| {
                let job = sc.spawn(|| this.pass(&twin, r, w, left, start));
                let right = this.pass(&actor, r, w, right, start);
                (
                    job.join().unwrap_or_else(|e| std::panic::resume_unwind(e)),
                    right,
                )
            });
            let gl = transfer_gradients(&twin, gl, &actor);
            let wl = left.len() as f32 / w.envs.len() as f32;
            let grads = weighted_sum(&actor, gl, wl, gr, 1.0 - wl);
            (grads, f64::from(wl) * vl + f64::from(1.0 - wl) * vr)
        };
        let actor = self
            .optim
            .step(warm.round_learning_rate(round), actor, grads);
        Ok((actor, value))
    }
}
