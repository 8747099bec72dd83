//! Perturbations the referee flies a policy under (docs/DESIGN.md "Perturbations"): a
//! jittered start, a model that is off by a few percent, motor lag, action latency and a
//! noisy state estimate. They measure how far a policy keeps flying from the one nominal
//! flight it was trained on.
//!
//! **What each applies to.** The start jitter moves every drone's spawn (it changes the
//! scenario, not the ego); the model, the latency and the sensor noise are the **ego's** (the
//! opponent stays the nominal reference it was trained against). Sensor noise is added to
//! the ego's state as every controller receives it (its own observation and, in a race, the
//! opponent's view of it), white and independent per step and axis; a real estimator's errors
//! are correlated in time, so this is a floor on what a flight sees, not a model of it.
//!
//! **Draws.** Per episode, the model and the latency are drawn once (uniformly in their
//! spans) and hold through every restart; the jitter is drawn at every spawn, the noise at
//! every step. Each comes from its own seeded stream, apart from the spawn draws: with
//! [`Perturbation::NONE`] an episode is bit for bit the unperturbed one, and adding a
//! perturbation never moves where the drones spawn.

use crate::dynamics::Preset;
use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::{MotorCommand, VehicleState};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// A closed interval drawn uniformly once per episode; `lo == hi` is a fixed value.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Span {
    /// Lower end.
    pub lo: f32,
    /// Upper end (≥ `lo`).
    pub hi: f32,
}

impl Span {
    /// The fixed value `v`.
    pub const fn fixed(v: f32) -> Self {
        Self { lo: v, hi: v }
    }

    fn is_fixed_at(&self, v: f32) -> bool {
        self.lo == v && self.hi == v
    }

    fn draw(&self, rng: &mut ChaCha8Rng) -> f32 {
        if self.hi > self.lo {
            rng.random_range(self.lo..=self.hi)
        } else {
            self.lo
        }
    }

    fn check(&self, what: &str, min: f32, max: f32) -> Result<(), String> {
        if !(self.lo.is_finite() && self.hi.is_finite()) {
            return Err(format!("{what}: must be finite numbers"));
        }
        if self.lo > self.hi {
            return Err(format!(
                "{what}: the span {}:{} is reversed",
                self.lo, self.hi
            ));
        }
        if self.lo < min || self.hi > max {
            return Err(format!("{what}: must lie in [{min}, {max}]"));
        }
        Ok(())
    }
}

/// The jitter of a spawn: each drone's start moved uniformly within these bounds, per axis.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StartJitter {
    /// Position offset per axis, uniform in ±this (m).
    pub position_m: f32,
    /// Roll, pitch and yaw offsets, each uniform in ±this (rad).
    pub attitude_rad: f32,
    /// Velocity per axis, uniform in ±this (m/s); the body rates stay 0.
    pub velocity_mps: f32,
}

impl StartJitter {
    /// `sitl eval --jitter` without a value: a few centimetres, a few degrees and a slow
    /// drift, what a hand-placed drone on a launch pad shows (5 cm, 5°, 0.2 m/s).
    pub const STANDARD: Self = Self {
        position_m: 0.05,
        attitude_rad: 5.0 * core::f32::consts::PI / 180.0,
        velocity_mps: 0.2,
    };

    fn is_zero(&self) -> bool {
        *self == Self::default()
    }

    /// `state` moved by one draw of the jitter.
    pub fn apply(&self, state: &VehicleState, rng: &mut ChaCha8Rng) -> VehicleState {
        let mut u = |r: f32| {
            if r > 0.0 {
                rng.random_range(-r..=r)
            } else {
                0.0
            }
        };
        let dp = Vec3::new(u(self.position_m), u(self.position_m), u(self.position_m));
        let (roll, pitch, yaw) = (
            u(self.attitude_rad),
            u(self.attitude_rad),
            u(self.attitude_rad),
        );
        let dv = Vec3::new(
            u(self.velocity_mps),
            u(self.velocity_mps),
            u(self.velocity_mps),
        );
        let turn = Quat::from_axis_angle(Vec3::Z, yaw)
            * Quat::from_axis_angle(Vec3::Y, pitch)
            * Quat::from_axis_angle(Vec3::X, roll);
        VehicleState {
            position_m: state.position_m + dp,
            attitude: (state.attitude * turn).normalized(),
            velocity_mps: state.velocity_mps + dv,
            body_rates_radps: state.body_rates_radps,
        }
    }
}

/// White Gaussian noise on the ego's state estimate: standard deviations per axis.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct SensorNoise {
    /// Position (m).
    pub position_m: f32,
    /// Velocity (m/s).
    pub velocity_mps: f32,
    /// Attitude: a rotation of this standard deviation per body axis (rad).
    pub attitude_rad: f32,
    /// Body rates (rad/s).
    pub rates_radps: f32,
}

impl SensorNoise {
    /// Level 1 of `--perturb noise=K`: the order of a Crazyflie 2.x's estimate in flight with
    /// Lighthouse or motion-capture positioning: 5 mm, 0.05 m/s, 0.01 rad (0.6°) and
    /// 0.05 rad/s (gyro noise under propeller vibration).
    pub const CRAZYFLIE: Self = Self {
        position_m: 0.005,
        velocity_mps: 0.05,
        attitude_rad: 0.01,
        rates_radps: 0.05,
    };

    /// Every deviation times `k`.
    pub fn times(self, k: f32) -> Self {
        Self {
            position_m: self.position_m * k,
            velocity_mps: self.velocity_mps * k,
            attitude_rad: self.attitude_rad * k,
            rates_radps: self.rates_radps * k,
        }
    }

    fn is_zero(&self) -> bool {
        *self == Self::default()
    }

    /// `state` as a noisy estimator reports it.
    pub fn apply(&self, state: &VehicleState, rng: &mut ChaCha8Rng) -> VehicleState {
        let mut v = |s: f32| {
            if s > 0.0 {
                Vec3::new(normal(rng) * s, normal(rng) * s, normal(rng) * s)
            } else {
                Vec3::ZERO
            }
        };
        let dp = v(self.position_m);
        let dv = v(self.velocity_mps);
        let dr = v(self.attitude_rad);
        let dw = v(self.rates_radps);
        let angle = dr.norm();
        let attitude = if angle > 0.0 {
            (state.attitude * Quat::from_axis_angle(dr.scale(1.0 / angle), angle)).normalized()
        } else {
            state.attitude
        };
        VehicleState {
            position_m: state.position_m + dp,
            attitude,
            velocity_mps: state.velocity_mps + dv,
            body_rates_radps: state.body_rates_radps + dw,
        }
    }
}

/// A standard normal sample (Box–Muller), the one every random perturbation and the
/// trainers' exploration noise draw.
pub fn normal(rng: &mut ChaCha8Rng) -> f32 {
    let u1: f32 = rng.random_range(f32::EPSILON..1.0);
    let u2: f32 = rng.random::<f32>();
    (-2.0 * u1.ln()).sqrt() * (core::f32::consts::TAU * u2).cos()
}

/// How an evaluation perturbs its episodes. [`Perturbation::NONE`] is the referee's
/// nominal flight.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Perturbation {
    /// Jitter of every spawn (start and restarts) of every drone.
    pub jitter: StartJitter,
    /// Factor on the ego's propeller force and torque (1 = the preset's).
    pub thrust_scale: Span,
    /// Factor on the ego's mass.
    pub mass_scale: Span,
    /// Factor on the ego's three moments of inertia.
    pub inertia_scale: Span,
    /// The ego's first-order motor time constant (s), replacing the preset's; `None` keeps it.
    pub motor_time_constant_s: Option<Span>,
    /// Control steps between the ego's command and the motors receiving it, drawn per
    /// episode in `[lo, hi]`; until the first command arrives the motors stay stopped.
    pub latency_steps: [u32; 2],
    /// Noise on the ego's state estimate.
    pub sensor_noise: SensorNoise,
}

impl Default for Perturbation {
    fn default() -> Self {
        Self::NONE
    }
}

/// Longest latency accepted (steps): 1 s at 50 Hz.
pub const MAX_LATENCY_STEPS: u32 = 50;

impl Perturbation {
    /// No perturbation: the referee's nominal flight.
    pub const NONE: Self = Self {
        jitter: StartJitter {
            position_m: 0.0,
            attitude_rad: 0.0,
            velocity_mps: 0.0,
        },
        thrust_scale: Span::fixed(1.0),
        mass_scale: Span::fixed(1.0),
        inertia_scale: Span::fixed(1.0),
        motor_time_constant_s: None,
        latency_steps: [0, 0],
        sensor_noise: SensorNoise {
            position_m: 0.0,
            velocity_mps: 0.0,
            attitude_rad: 0.0,
            rates_radps: 0.0,
        },
    };

    /// The nominal flight from jittered starts ([`StartJitter::STANDARD`], `--jitter` alone):
    /// the base of the robustness levels and of a trainer's jittered evaluation.
    pub const JITTERED: Self = Self {
        jitter: StartJitter::STANDARD,
        ..Self::NONE
    };

    /// True for [`Perturbation::NONE`] (and anything equal to it).
    pub fn is_none(&self) -> bool {
        *self == Self::NONE
    }

    /// A clear error for values no flight can mean: non-finite numbers, reversed spans,
    /// scales outside (0.1, 10], a motor lag beyond 1 s, latency beyond
    /// [`MAX_LATENCY_STEPS`], negative noise or jitter, a jitter beyond 1 m, 90° or 5 m/s.
    pub fn validate(&self) -> Result<(), String> {
        self.thrust_scale.check("thrust", 0.1, 10.0)?;
        self.mass_scale.check("mass", 0.1, 10.0)?;
        self.inertia_scale.check("inertia", 0.1, 10.0)?;
        if let Some(t) = &self.motor_time_constant_s {
            t.check("motor-tau-ms (as seconds)", 0.0, 1.0)?;
        }
        let [a, b] = self.latency_steps;
        if a > b {
            return Err(format!("latency: the span {a}:{b} is reversed"));
        }
        if b > MAX_LATENCY_STEPS {
            return Err(format!(
                "latency: at most {MAX_LATENCY_STEPS} control steps (1 s), not {b}"
            ));
        }
        let n = &self.sensor_noise;
        for (what, v, max) in [
            ("noise-pos (m)", n.position_m, 1.0),
            ("noise-vel (m/s)", n.velocity_mps, 10.0),
            ("noise attitude (rad)", n.attitude_rad, 1.0),
            ("noise-rate (rad/s)", n.rates_radps, 10.0),
            ("jitter pos (m)", self.jitter.position_m, 1.0),
            (
                "jitter attitude (rad)",
                self.jitter.attitude_rad,
                core::f32::consts::FRAC_PI_2,
            ),
            ("jitter vel (m/s)", self.jitter.velocity_mps, 5.0),
        ] {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return Err(format!("{what}: must be a number in [0, {max}], not {v}"));
            }
        }
        Ok(())
    }

    /// Parses `--perturb`: comma-separated `KEY=VALUE`, a value `X` (fixed) or `LO:HI` (drawn
    /// per episode), on top of `self`:
    ///
    /// | key | value |
    /// |---|---|
    /// | `thrust`, `mass`, `inertia` | factors on the ego's preset (1 = nominal) |
    /// | `motor-tau-ms` | the ego's motor time constant (ms) |
    /// | `latency` | steps of 20 ms between command and motors |
    /// | `noise` | sensor noise as a multiple of [`SensorNoise::CRAZYFLIE`] |
    /// | `noise-pos`, `noise-vel`, `noise-att-deg`, `noise-rate` | one deviation (m, m/s, °, rad/s) |
    ///
    /// The result is validated ([`Perturbation::validate`]).
    pub fn parse_onto(mut self, spec: &str) -> Result<Self, String> {
        for item in key_values(spec, "") {
            let (key, value) = item?;
            let span = || parse_span(key, value);
            let single = || -> Result<f32, String> {
                let s = span()?;
                if s.lo == s.hi {
                    Ok(s.lo)
                } else {
                    Err(format!("{key}: takes one value, not a span"))
                }
            };
            match key {
                "thrust" => self.thrust_scale = span()?,
                "mass" => self.mass_scale = span()?,
                "inertia" => self.inertia_scale = span()?,
                "motor-tau-ms" => {
                    let s = span()?;
                    self.motor_time_constant_s = Some(Span {
                        lo: s.lo / 1000.0,
                        hi: s.hi / 1000.0,
                    });
                }
                "latency" => {
                    let s = span()?;
                    let steps = |v: f32| -> Result<u32, String> {
                        if v >= 0.0 && v.fract() == 0.0 && v <= MAX_LATENCY_STEPS as f32 {
                            Ok(v as u32)
                        } else {
                            Err(format!(
                                "latency: whole control steps in [0, {MAX_LATENCY_STEPS}], not {v}"
                            ))
                        }
                    };
                    self.latency_steps = [steps(s.lo)?, steps(s.hi)?];
                }
                "noise" => {
                    let k = single()?;
                    if !(k.is_finite() && k >= 0.0) {
                        return Err(format!("noise: a multiple >= 0, not {k}"));
                    }
                    self.sensor_noise = SensorNoise::CRAZYFLIE.times(k);
                }
                "noise-pos" => self.sensor_noise.position_m = single()?,
                "noise-vel" => self.sensor_noise.velocity_mps = single()?,
                "noise-att-deg" => self.sensor_noise.attitude_rad = single()?.to_radians(),
                "noise-rate" => self.sensor_noise.rates_radps = single()?,
                _ => {
                    return Err(format!(
                        "unknown perturbation '{key}' (thrust, mass, inertia, motor-tau-ms, latency, noise, noise-pos, noise-vel, noise-att-deg, noise-rate)"
                    ));
                }
            }
        }
        self.validate()?;
        Ok(self)
    }

    /// Parses `--jitter`'s value onto `self.jitter`: empty for [`StartJitter::STANDARD`], else
    /// comma-separated `pos=M`, `att-deg=DEG`, `vel=MPS` (unnamed parts stay 0).
    pub fn with_jitter(mut self, spec: &str) -> Result<Self, String> {
        if spec.trim().is_empty() {
            self.jitter = StartJitter::STANDARD;
        } else {
            let mut j = StartJitter::default();
            for item in key_values(spec, "--jitter ") {
                let (key, value) = item?;
                let v: f32 = value
                    .trim()
                    .parse()
                    .map_err(|_| format!("--jitter {key}: '{value}' is not a number"))?;
                match key {
                    "pos" => j.position_m = v,
                    "att-deg" => j.attitude_rad = v.to_radians(),
                    "vel" => j.velocity_mps = v,
                    _ => {
                        return Err(format!("--jitter: unknown key '{key}' (pos, att-deg, vel)"));
                    }
                }
            }
            self.jitter = j;
        }
        self.validate()?;
        Ok(self)
    }

    /// A short description for reports, e.g. `jitter 5 cm/5°/0.2 m/s, thrust 0.95-1.05`;
    /// "none" for [`Perturbation::NONE`].
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        let j = &self.jitter;
        if !j.is_zero() {
            parts.push(format!(
                "jitter {:.0} cm/{:.0}°/{:.2} m/s",
                j.position_m * 100.0,
                j.attitude_rad.to_degrees(),
                j.velocity_mps
            ));
        }
        let span = |s: &Span, k: f32| {
            if s.lo == s.hi {
                format!("{}", s.lo * k)
            } else {
                format!("{}-{}", s.lo * k, s.hi * k)
            }
        };
        for (name, s) in [
            ("thrust", &self.thrust_scale),
            ("mass", &self.mass_scale),
            ("inertia", &self.inertia_scale),
        ] {
            if !s.is_fixed_at(1.0) {
                parts.push(format!("{name} x{}", span(s, 1.0)));
            }
        }
        if let Some(t) = &self.motor_time_constant_s {
            parts.push(format!("motor lag {} ms", span(t, 1e3)));
        }
        let [a, b] = self.latency_steps;
        if b > 0 {
            parts.push(if a == b {
                format!("latency {a} steps")
            } else {
                format!("latency {a}-{b} steps")
            });
        }
        let n = &self.sensor_noise;
        if !n.is_zero() {
            parts.push(format!(
                "noise {} mm/{} m/s/{:.2}°/{} rad/s",
                n.position_m * 1e3,
                n.velocity_mps,
                n.attitude_rad.to_degrees(),
                n.rates_radps
            ));
        }
        if parts.is_empty() {
            "none".into()
        } else {
            parts.join(", ")
        }
    }

    /// The draws of episode `index` of an evaluation seeded `seed`.
    pub fn episode(&self, preset: &Preset, seed: u64, index: u64) -> EpisodePerturbation {
        let stream = |key: u64| {
            let mut r = ChaCha8Rng::seed_from_u64(seed ^ key);
            r.set_stream(index);
            r
        };
        let mut model = stream(0x7065_7274_6d6f_6465); // "pertmode"
        let mut ego = *preset;
        if !self.thrust_scale.is_fixed_at(1.0) {
            ego.thrust_scale *= self.thrust_scale.draw(&mut model);
        }
        if !self.mass_scale.is_fixed_at(1.0) {
            ego.mass_kg *= self.mass_scale.draw(&mut model);
        }
        if !self.inertia_scale.is_fixed_at(1.0) {
            let k = self.inertia_scale.draw(&mut model);
            ego.inertia_kgm2 = ego.inertia_kgm2.map(|j| j * k);
        }
        if let Some(t) = &self.motor_time_constant_s {
            ego.motor_time_constant_s = t.draw(&mut model);
        }
        let [a, b] = self.latency_steps;
        let latency = if b > a { model.random_range(a..=b) } else { a };
        EpisodePerturbation {
            jitter: self.jitter,
            noise: self.sensor_noise,
            ego_preset: ego,
            latency_steps: latency,
            pending: VecDeque::new(),
            jitter_rng: stream(0x7065_7274_6a69_7474), // "pertjitt"
            noise_rng: stream(0x7065_7274_6e6f_6973),  // "pertnois"
            drawn_from: (seed, index),
        }
    }

    /// The episode [`EpisodePerturbation::snapshot`] saw, drawn again from this
    /// perturbation on `preset` and moved to where it was.
    pub fn restore(&self, preset: &Preset, s: &EpisodePerturbationSnapshot) -> EpisodePerturbation {
        let mut e = self.episode(preset, s.seed, s.index);
        e.pending = s.pending.iter().copied().collect();
        e.jitter_rng.set_word_pos(s.jitter_word_pos);
        e.noise_rng.set_word_pos(s.noise_word_pos);
        e
    }
}

/// A [`Perturbation`] as a config writes it: `--perturb`'s text, kept as written (it is part
/// of a training config's hash), with its parsed value. (De)serialised as the text.
#[derive(Clone, Debug, PartialEq)]
pub struct PerturbSpec {
    text: String,
    value: Perturbation,
}

impl PerturbSpec {
    /// Parses `text` as `--perturb` does ([`Perturbation::parse_onto`] on none).
    pub fn parse(text: &str) -> Result<Self, String> {
        Ok(Self {
            value: Perturbation::NONE.parse_onto(text)?,
            text: text.to_string(),
        })
    }

    /// The perturbation.
    pub fn value(&self) -> &Perturbation {
        &self.value
    }
}

/// (De)serialises a spec type as its `text`, parsed back by its `parse` (whose error is
/// the deserialiser's): [`PerturbSpec`] and [`JitterSpec`].
macro_rules! serde_as_text {
    ($spec:ty) => {
        impl Serialize for $spec {
            fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.serialize_str(&self.text)
            }
        }

        impl<'de> Deserialize<'de> for $spec {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let text = String::deserialize(d)?;
                Self::parse(&text).map_err(serde::de::Error::custom)
            }
        }
    };
}

serde_as_text!(PerturbSpec);

/// A [`StartJitter`] as a config writes it: `sitl eval --jitter`'s value (`""` for
/// [`StartJitter::STANDARD`], else `pos=M,att-deg=DEG,vel=MPS`), kept as written (it is part
/// of a training config's hash), with its parsed value. (De)serialised as the text.
#[derive(Clone, Debug, PartialEq)]
pub struct JitterSpec {
    text: String,
    value: StartJitter,
}

impl JitterSpec {
    /// Parses `text` as `--jitter` does ([`Perturbation::with_jitter`], its bounds checked).
    pub fn parse(text: &str) -> Result<Self, String> {
        Ok(Self {
            value: Perturbation::NONE.with_jitter(text)?.jitter,
            text: text.to_string(),
        })
    }

    /// The jitter.
    pub fn value(&self) -> &StartJitter {
        &self.value
    }
}

serde_as_text!(JitterSpec);

/// The comma-separated `KEY=VALUE` items of `spec` (empty items skipped); an item without
/// `=` is an error, prefixed with `what`.
fn key_values<'a>(
    spec: &'a str,
    what: &'a str,
) -> impl Iterator<Item = Result<(&'a str, &'a str), String>> + 'a {
    spec.split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(move |item| {
            item.split_once('=')
                .ok_or_else(|| format!("{what}'{item}': expected KEY=VALUE"))
        })
}

fn parse_span(key: &str, value: &str) -> Result<Span, String> {
    let num = |s: &str| -> Result<f32, String> {
        match s.trim().parse::<f32>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(format!("{key}: '{s}' is not a finite number")),
        }
    };
    match value.split_once(':') {
        Some((lo, hi)) => Ok(Span {
            lo: num(lo)?,
            hi: num(hi)?,
        }),
        None => Ok(Span::fixed(num(value)?)),
    }
}

/// One episode's draws of a [`Perturbation`], and its latency queue: what the episode
/// runner ([`crate::referee::run_crew`]) applies to the ego.
#[derive(Clone, Debug)]
pub struct EpisodePerturbation {
    jitter: StartJitter,
    noise: SensorNoise,
    /// The ego's airframe in this episode.
    pub ego_preset: Preset,
    /// The ego's command latency in this episode (control steps).
    pub latency_steps: u32,
    pending: VecDeque<MotorCommand>,
    jitter_rng: ChaCha8Rng,
    noise_rng: ChaCha8Rng,
    /// The draw's seed and index ([`Perturbation::episode`]), for [`Self::snapshot`].
    drawn_from: (u64, u64),
}

/// What an episode's perturbation has consumed so far ([`EpisodePerturbation::snapshot`]):
/// with the [`Perturbation`] and preset it was drawn from, the episode exactly as it is.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpisodePerturbationSnapshot {
    seed: u64,
    index: u64,
    pending: Vec<MotorCommand>,
    jitter_word_pos: u128,
    noise_word_pos: u128,
}

impl EpisodePerturbation {
    /// A spawn state, jittered (unchanged without jitter).
    pub fn spawn(&mut self, state: VehicleState) -> VehicleState {
        if self.jitter.is_zero() {
            state
        } else {
            self.jitter.apply(&state, &mut self.jitter_rng)
        }
    }

    /// A new flight: the commands in flight are lost and the motors wait, stopped, for the
    /// first one.
    pub fn restart(&mut self) {
        self.restart_turning(MotorCommand::STOP);
    }

    /// A new flight whose propellers turn at `now` (a training replay of a state in flight):
    /// the motors receive `now` until the first command arrives.
    pub fn restart_turning(&mut self, now: MotorCommand) {
        self.pending.clear();
        self.pending.extend((0..self.latency_steps).map(|_| now));
    }

    /// The ego's state as its estimator reports it.
    pub fn sense(&mut self, state: VehicleState) -> VehicleState {
        if self.noise.is_zero() {
            state
        } else {
            self.noise.apply(&state, &mut self.noise_rng)
        }
    }

    /// Where this episode's draws stand ([`Perturbation::restore`] puts it back).
    pub fn snapshot(&self) -> EpisodePerturbationSnapshot {
        EpisodePerturbationSnapshot {
            seed: self.drawn_from.0,
            index: self.drawn_from.1,
            pending: self.pending.iter().copied().collect(),
            jitter_word_pos: self.jitter_rng.get_word_pos(),
            noise_word_pos: self.noise_rng.get_word_pos(),
        }
    }

    /// The command the ego's motors receive this step, given the one its controller sent.
    pub fn deliver(&mut self, sent: MotorCommand) -> MotorCommand {
        if self.latency_steps == 0 {
            return sent;
        }
        self.pending.push_back(sent);
        self.pending.pop_front().unwrap_or(MotorCommand::STOP)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_spans_and_refuses_nonsense() {
        let p = Perturbation::NONE
            .parse_onto("thrust=0.9:1.1, mass=1.05, latency=1:2, noise=2, motor-tau-ms=20")
            .unwrap();
        assert_eq!(p.thrust_scale, Span { lo: 0.9, hi: 1.1 });
        assert_eq!(p.mass_scale, Span::fixed(1.05));
        assert_eq!(p.latency_steps, [1, 2]);
        assert_eq!(p.sensor_noise, SensorNoise::CRAZYFLIE.times(2.0));
        assert_eq!(p.motor_time_constant_s, Some(Span::fixed(0.02)));
        for bad in [
            "mass=-1",
            "mass=nan",
            "thrust=1.1:0.9",
            "latency=1.5",
            "latency=51",
            "noise=-1",
            "noise=1:2",
            "noise-pos=inf",
            "gravity=2",
            "thrust",
            "motor-tau-ms=2000",
        ] {
            let e = Perturbation::NONE.parse_onto(bad);
            assert!(e.is_err(), "{bad} was accepted: {e:?}");
        }
        assert!(Perturbation::NONE.with_jitter("pos=-0.1").is_err());
        assert!(Perturbation::NONE.with_jitter("pos=0.1,spin=3").is_err());
        assert_eq!(
            Perturbation::NONE.with_jitter("").unwrap().jitter,
            StartJitter::STANDARD
        );
        assert_eq!(Perturbation::NONE.describe(), "none");
        assert!(Perturbation::NONE.parse_onto("").unwrap().is_none());
    }

    #[test]
    fn draws_are_seeded_per_episode_and_stay_in_their_spans() {
        let p = Perturbation::NONE
            .parse_onto("thrust=0.9:1.1,inertia=0.8:1.2,latency=0:3")
            .unwrap();
        let preset = Preset::paper();
        let a = p.episode(&preset, 7, 3);
        let b = p.episode(&preset, 7, 3);
        assert_eq!(a.ego_preset, b.ego_preset);
        assert_eq!(a.latency_steps, b.latency_steps);
        let mut seen = std::collections::BTreeSet::new();
        for i in 0..200 {
            let e = p.episode(&preset, 7, i);
            let k = e.ego_preset.thrust_scale / preset.thrust_scale;
            assert!((0.9 - 1e-6..=1.1 + 1e-6).contains(&k), "{k}");
            let j = e.ego_preset.inertia_kgm2[0] / preset.inertia_kgm2[0];
            assert!((0.8 - 1e-6..=1.2 + 1e-6).contains(&j), "{j}");
            assert_eq!(e.ego_preset.mass_kg, preset.mass_kg);
            seen.insert(e.latency_steps);
        }
        assert_eq!(seen.into_iter().collect::<Vec<_>>(), vec![0, 1, 2, 3]);
    }

    #[test]
    fn latency_delays_commands_and_starts_stopped() {
        let p = Perturbation::NONE.parse_onto("latency=2").unwrap();
        let mut e = p.episode(&Preset::paper(), 0, 0);
        e.restart();
        let c = |r: f32| MotorCommand { rpm: [r; 4] };
        assert_eq!(e.deliver(c(1.0)), MotorCommand::STOP);
        assert_eq!(e.deliver(c(2.0)), MotorCommand::STOP);
        assert_eq!(e.deliver(c(3.0)), c(1.0));
        assert_eq!(e.deliver(c(4.0)), c(2.0));
        e.restart();
        assert_eq!(e.deliver(c(5.0)), MotorCommand::STOP);
    }

    #[test]
    fn jitter_and_noise_stay_near_the_state() {
        let p = Perturbation::NONE
            .with_jitter("")
            .unwrap()
            .parse_onto("noise=1")
            .unwrap();
        let mut e = p.episode(&Preset::paper(), 1, 0);
        let s = VehicleState::at_rest(Vec3::new(1.0, 2.0, 1.0), Quat::from_yaw(0.3));
        let mut max_dp: f32 = 0.0;
        let mut sum_dv = 0.0f64;
        for _ in 0..2000 {
            let j = e.spawn(s);
            let d = j.position_m - s.position_m;
            assert!(d.x.abs() <= 0.05 && d.y.abs() <= 0.05 && d.z.abs() <= 0.05);
            max_dp = max_dp.max(d.x.abs());
            assert!(j.velocity_mps.x.abs() <= 0.2);
            let tilt = j.attitude.rotate(Vec3::Z).dot(Vec3::Z);
            assert!(tilt >= (2.0f32 * 5.0f32.to_radians()).cos() - 1e-4);
            let n = e.sense(s);
            sum_dv += f64::from(n.velocity_mps.x).powi(2);
        }
        assert!(max_dp > 0.045, "the jitter uses its range: {max_dp}");
        let std = (sum_dv / 2000.0).sqrt();
        assert!((std - 0.05).abs() < 0.005, "velocity noise std {std}");
    }
}
