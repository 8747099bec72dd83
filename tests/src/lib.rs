//! Cross-crate integration tests of Overtake (see `tests/tests/`), and the shared fixtures
//! they use: seeded weights for every Table 1 architecture and an independent float64
//! reference implementation of the policies ([`mod@reference`]).
#![deny(missing_docs)]

pub mod fixtures;
pub mod reference;
