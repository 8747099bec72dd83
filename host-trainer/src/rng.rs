//! The run's random number generators: one seeded ChaCha8 stream per purpose (network
//! initialisation, action noise, minibatch order, the guard's test rollouts), so that a
//! seed fixes a run and a checkpoint can store and restore each stream's position.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The generator of stream `stream` of `seed`.
pub fn generator(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream);
    r
}

/// The generator of the network initialisation for `seed` (its own stream, apart from the
/// environment's and the action noise's).
pub fn init_rng(seed: u64) -> ChaCha8Rng {
    generator(seed, u64::MAX)
}

/// A standard normal sample (Box–Muller): sitl's, which its perturbations draw too.
pub use sitl::perturb::normal;

/// A generator's position as text (`stream:word`), for a checkpoint's `state.json`.
pub fn rng_state(r: &ChaCha8Rng) -> String {
    format!("{}:{}", r.get_stream(), r.get_word_pos())
}

/// The generator of `seed` at the position [`rng_state`] wrote; `None` when `s` is not one.
pub fn restore_rng(seed: u64, s: &str) -> Option<ChaCha8Rng> {
    let (stream, pos) = s.split_once(':')?;
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream.parse().ok()?);
    r.set_word_pos(pos.parse().ok()?);
    Some(r)
}
