//! Shared by the preprocessor's test files: [`skip_or_fail`], through which
//! every skip for missing real data (`../shared/data`) goes.

/// Skips a test that cannot run here (no `../shared/data`, no `/proc`): prints
/// `reason` and returns, so that the caller returns. Under `PLANET_CI=1` (set
/// by `.ci/run`) or `PLANET_REQUIRE_ALL=1` it panics instead: in CI a skip is
/// a failure.
pub fn skip_or_fail(reason: &str) {
    let set = |v: &str| std::env::var(v).is_ok_and(|x| x == "1");
    if set("PLANET_CI") || set("PLANET_REQUIRE_ALL") {
        panic!("{reason} (PLANET_CI or PLANET_REQUIRE_ALL is set: a skip fails)");
    }
    eprintln!("note: skipped, {reason}");
}
