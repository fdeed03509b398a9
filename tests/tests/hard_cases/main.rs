//! The hard-case suite (`docs/HARD_CASES.md`): every case has an analytic or invariant
//! reference and a stated tolerance, and runs in process on the CPU (SIMD packets and the
//! scalar march), on the GPU (any wgpu adapter; lavapipe in CI) and distributed over worker
//! processes. No case may put NaN or Inf into a pixel. The suite prints one line per case
//! and backend (measured error against tolerance) and one summary line per backend.
//!
//! `cargo test --test hard_cases -- [FILTER] [--backend cpu|cpu-scalar|gpu|distributed]`
//! runs the cases whose number or name contains FILTER on the chosen backends.

mod classification;
mod compositing;
mod geometry;
mod harness;
mod lod;
mod numerics;
mod precision;
mod shapes;

use harness::{Backend, Ctx, Res};
use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::time::Instant;

/// One hard case.
pub struct Case {
    /// Its number in `docs/HARD_CASES.md`.
    pub no: u32,
    /// Short name (kebab case).
    pub name: &'static str,
    /// What the image is compared with.
    pub reference: &'static str,
    /// Largest error allowed, in the unit `run` measures.
    pub tol: f64,
    /// Why that tolerance.
    pub why: &'static str,
    /// Rays of more than 16 000 samples. llvmpipe (lavapipe) stops every shader loop nest
    /// after 65 535 back-edges and so cuts such rays short: there the case runs with
    /// [`Ctx::short_loops`] set, and shortens its rays under that limit.
    pub long_rays: bool,
    /// Renders and returns the measured error (an `Err` for a broken invariant that has no
    /// magnitude, such as a NaN pixel or a refused scene).
    pub run: fn(&Ctx) -> Res<f64>,
}

fn all_cases() -> Vec<Case> {
    let mut v = Vec::new();
    v.extend(precision::cases());
    v.extend(geometry::cases());
    v.extend(numerics::cases());
    v.extend(shapes::cases());
    v.extend(compositing::cases());
    v.extend(lod::cases());
    v.extend(classification::cases());
    v.extend(geometry::later_cases());
    v
}

/// Every case has a numbered row `| no | name |` in docs/HARD_CASES.md, in order, and the
/// table has no other rows.
fn check_docs(cases: &[Case]) -> Res<()> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/HARD_CASES.md");
    let text = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    let rows: Vec<(u32, String)> = text
        .lines()
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let no = cells.get(1)?.parse::<u32>().ok()?;
            Some((no, cells.get(2)?.trim_matches('`').to_string()))
        })
        .collect();
    let want: Vec<(u32, String)> = cases.iter().map(|c| (c.no, c.name.to_string())).collect();
    if rows != want {
        return Err(format!(
            "{path}: its numbered rows {rows:?} do not list the suite's cases {want:?}"
        ));
    }
    Ok(())
}

fn main() {
    let mut filter: Option<String> = None;
    let mut backends: Vec<Backend> = Backend::ALL.to_vec();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--backend" => {
                let b = args.next().unwrap_or_default();
                backends = Backend::ALL.into_iter().filter(|x| x.name() == b).collect();
                if backends.is_empty() {
                    eprintln!(
                        "error: --backend takes cpu, cpu-scalar, gpu or distributed, not {b:?}"
                    );
                    std::process::exit(2);
                }
            }
            // libtest flags that cargo may pass through.
            s if s.starts_with("--") => {}
            s => filter = Some(s.to_string()),
        }
    }
    let cases = all_cases();
    let mut failed_total = 0;
    if let Err(e) = check_docs(&cases) {
        eprintln!("FAILED docs: {e}");
        failed_total += 1;
    }
    let mut numbers: Vec<u32> = cases.iter().map(|c| c.no).collect();
    numbers.dedup();
    if numbers.len() != cases.len() || numbers.windows(2).any(|w| w[0] >= w[1]) {
        eprintln!("FAILED: case numbers must be unique and increasing");
        failed_total += 1;
    }
    let selected: Vec<&Case> = cases
        .iter()
        .filter(|c| {
            filter
                .as_deref()
                .is_none_or(|f| c.name.contains(f) || c.no.to_string() == f.trim_start_matches('#'))
        })
        .collect();
    let rt = Arc::new(
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("tokio runtime"),
    );
    let gpu = backends.contains(&Backend::Gpu) && strata_tests::scenes::gpu_available();
    // Panics inside a case are reported as that case's failure, not as a crash.
    std::panic::set_hook(Box::new(|_| {}));
    let mut summary = Vec::new();
    for &b in &backends {
        if b == Backend::Gpu && !gpu {
            summary.push(format!(
                "hard cases [{}]: skipped, no wgpu adapter",
                b.name()
            ));
            continue;
        }
        let (mut passed, mut failed, mut shortened) = (0, 0, 0);
        let llvmpipe = b == Backend::Gpu
            && strata_worker::gpu::list_adapters()
                .iter()
                .all(|a| a.3 && a.1.contains("llvmpipe"));
        let t_backend = Instant::now();
        for c in &selected {
            let short = llvmpipe && c.long_rays;
            if short {
                shortened += 1;
                println!(
                    "note   #{:02} {:<34} {:<12} rays shortened: llvmpipe stops shader loops after 65 535 iterations",
                    c.no,
                    c.name,
                    b.name()
                );
            }
            let t = Instant::now();
            let mut ctx = Ctx::new(b, rt.clone());
            ctx.short_loops = short;
            let r = std::panic::catch_unwind(AssertUnwindSafe(|| (c.run)(&ctx)));
            let secs = t.elapsed().as_secs_f64();
            let verdict = match r {
                Ok(Ok(err)) if err <= c.tol => Ok(format!("error {err:.3e} <= {:.1e}", c.tol)),
                Ok(Ok(err)) => Err(format!("error {err:.3e} > tolerance {:.1e}", c.tol)),
                Ok(Err(e)) => Err(e),
                Err(p) => Err(format!(
                    "panicked: {}",
                    p.downcast_ref::<String>()
                        .map(String::as_str)
                        .or(p.downcast_ref::<&str>().copied())
                        .unwrap_or("?")
                )),
            };
            match verdict {
                Ok(m) => {
                    passed += 1;
                    println!(
                        "ok     #{:02} {:<34} {:<12} {m} ({secs:.1} s)",
                        c.no,
                        c.name,
                        b.name()
                    );
                }
                Err(m) => {
                    failed += 1;
                    println!(
                        "FAILED #{:02} {:<34} {:<12} {m} ({secs:.1} s)",
                        c.no,
                        c.name,
                        b.name()
                    );
                }
            }
        }
        failed_total += failed;
        summary.push(format!(
            "hard cases [{}]: {passed} passed, {failed} failed, {shortened} with rays shortened ({:.0} s)",
            b.name(),
            t_backend.elapsed().as_secs_f64()
        ));
    }
    let _ = std::panic::take_hook();
    for s in &summary {
        println!("{s}");
    }
    if failed_total > 0 {
        std::process::exit(1);
    }
}
