//! The shipped policies the commands fly when none is named: one list, read by `sitl race`
//! and by the firmware images (`tools/stm32f405-fit` holds the same stage-1 and stage-2
//! policies; a test in `tools` keeps the two picks equal).

use std::path::PathBuf;

/// `sitl race`'s ego, the first of these in `policies/` that exists: the stage-2 (race)
/// policies in order of preference, then stage-1 ones.
pub const RACE_EGOS: [&str; 6] = [
    "stage2.blob",
    "stage2_transplant.blob",
    "stage2_G.blob",
    "stage1.blob",
    "stage1_guarded.blob",
    "stage1_imitation.blob",
];

/// The stage-1 policies a stage-2 ego races against, in order of preference: `sitl race`'s
/// opponent (never the ego itself).
pub const OPPONENTS: [&str; 2] = ["stage1.blob", "stage1_guarded.blob"];

/// The path of the first of `names` in `policies/` of the working directory, else of the
/// repository this crate was built from; `None` if there is none.
pub fn find(names: &[&str]) -> Option<PathBuf> {
    let dirs = [
        PathBuf::from("policies"),
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../policies"),
    ];
    dirs.iter()
        .flat_map(|d| names.iter().map(move |n| d.join(n)))
        .find(|p| p.is_file())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_race_policies_are_found_from_the_crate() {
        let ego = find(&RACE_EGOS).expect("a shipped ego");
        assert!(ego.ends_with(RACE_EGOS[0]), "{}", ego.display());
        let opponent = find(&OPPONENTS).expect("a shipped opponent");
        assert!(opponent.ends_with(OPPONENTS[0]), "{}", opponent.display());
        assert_eq!(find(&["no_such_policy.blob"]), None);
    }
}
