//! `strata-fuzz TARGET`: an AFL++ persistent-mode harness around one of
//! `strata_tests::fuzz::TARGETS` (see fuzz/README.md).

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    let Some(f) = strata_tests::fuzz::target(&name) else {
        let names: Vec<&str> = strata_tests::fuzz::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("usage: strata-fuzz TARGET (one of {})", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| {
        f(data);
    });
}
