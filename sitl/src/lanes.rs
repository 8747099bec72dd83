//! The host's batched inference ([`Policy::act_lanes`], [`Policy::step_lanes`],
//! [`Controller::step_lanes`]: [`LANES`] envs side by side) compiled for the widest vector
//! unit the CPU has: AVX-512, AVX2, else the SSE2 baseline. Every variant performs the same
//! operations in every lane, in the same order (no fused multiply-add), so each gives the
//! numbers of firmware-core's one-at-a-time `act` and `step` bit for bit, whichever runs
//! (NaNs aside: which operand's NaN an instruction keeps is its choice).
//!
//! The training rollout (host-trainer) flies the learner through these, and the race
//! environment flies its opponents through [`controller_step_lanes`].

use firmware_core::Controller;
use firmware_core::controller::StepOutput;
use firmware_core::nn::{ACTION_DIM, LANES};
use firmware_core::policy::{Policy, PolicyState};
use firmware_core::vehicle::VehicleState;

/// Means of [`LANES`] envs, one action per lane.
pub type LaneActions = [[f32; ACTION_DIM]; LANES];

/// Defines `$name`, which calls `$body` compiled for AVX-512, AVX2 or the baseline, as the
/// CPU allows (checked once per call: `is_x86_feature_detected!` caches its answer).
macro_rules! multiversion {
    ($(#[$doc:meta])* fn $name:ident<$lt:lifetime>($($arg:ident: $ty:ty),*) -> $ret:ty $body:block) => {
        $(#[$doc])*
        pub fn $name<$lt>($($arg: $ty),*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                fn avx512<$lt>($($arg: $ty),*) -> $ret $body
                #[target_feature(enable = "avx2")]
                fn avx2<$lt>($($arg: $ty),*) -> $ret $body
                if std::arch::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU has AVX-512F (checked just above).
                    return unsafe { avx512($($arg),*) };
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2 (checked just above).
                    return unsafe { avx2($($arg),*) };
                }
            }
            $body
        }
    };
}

multiversion! {
    /// [`Policy::act_lanes`]: a feed-forward policy on [`LANES`] observations (`None` for a
    /// recurrent policy or another length).
    fn act_lanes<'w>(policy: &Policy<'w>, obs: &[f32]) -> Option<LaneActions> {
        policy.act_lanes(obs)
    }
}

multiversion! {
    /// [`Policy::step_lanes`]: any policy on [`LANES`] observations, advancing each lane's
    /// recurrent state (`None`, nothing advanced, for another length or another policy's
    /// states).
    fn step_lanes<'w>(
        policy: &Policy<'w>,
        obs: &[f32],
        states: [&mut PolicyState; LANES]
    ) -> Option<LaneActions> {
        policy.step_lanes(obs, states)
    }
}

multiversion! {
    /// [`Controller::step_lanes`]: [`LANES`] controllers flying `policy` (clones of one
    /// controller), stepped side by side.
    fn controller_step_lanes<'w>(
        policy: &Policy<'w>,
        controllers: [&mut Controller<'w>; LANES],
        own: [&VehicleState; LANES],
        opponent: [Option<&VehicleState>; LANES]
    ) -> [StepOutput; LANES] {
        Controller::step_lanes(policy, controllers, own, opponent)
    }
}
