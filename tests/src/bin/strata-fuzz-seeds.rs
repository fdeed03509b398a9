//! `strata-fuzz-seeds DIR`: writes the fuzz targets' seed inputs (valid files and messages
//! from Strata's own writers) to `DIR/<target>/seed-<name>`, the fuzzer's starting corpus.

fn main() {
    let Some(dir) = std::env::args().nth(1) else {
        eprintln!("usage: strata-fuzz-seeds DIR");
        std::process::exit(2);
    };
    let dir = std::path::Path::new(&dir);
    for (target, name, bytes) in strata_tests::fuzz::seeds() {
        let d = dir.join(target);
        let p = d.join(format!("seed-{name}"));
        if let Err(e) = std::fs::create_dir_all(&d).and_then(|_| std::fs::write(&p, &bytes)) {
            eprintln!("error: {}: {e}", p.display());
            std::process::exit(1);
        }
        println!("{} ({} bytes)", p.display(), bytes.len());
    }
}
