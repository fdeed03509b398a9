//! `bench-resplit`: what a re-split of the k-d tree costs the coordinator between two frames
//! of a sequence, at the box counts of real surveys. A volume's cost field has one box per
//! level-0 brick: about 2 800 for the demo, 10⁵ for a 100 GB float survey in 64³ pages and
//! 10⁶ for a terabyte. The boxes here are such a survey's bricks (a grid of `--boxes` of
//! them, rotated by `--rotate` degrees about the vertical, as surveys on UTM grids are, so
//! that their world boxes overlap), with costs that vary smoothly across the survey; the
//! measurement is the split's own leaves timed by a second, different field (as a view
//! would), so that the re-split really moves.
//!
//! Reports the median over `--repeats` of each step: `Decomposition::balanced` (the split),
//! `imbalance_under` (the split's imbalance under another field), the per-leaf model's
//! `reweighted`, and a whole `decompose::resplit` with that model.
//!
//! ```text
//! cargo build --release -p strata-bench
//! ./target/release/bench-resplit --boxes 2800,100000,1000000 --workers 8,64
//! ```

use clap::Parser;
use std::time::Instant;
use strata_common::kd::{CostBox, Decomposition, Region};
use strata_coordinator::decompose::{resplit, Measurement, SceneCosts};

#[derive(Parser)]
#[command(name = "bench-resplit", version, about)]
struct Cli {
    /// Numbers of cost boxes (bricks), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "2800,100000,1000000")]
    boxes: Vec<usize>,
    /// Numbers of workers (one leaf each), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "8,64")]
    workers: Vec<usize>,
    /// Rotation of the survey grid about the vertical, in degrees.
    #[arg(long, default_value_t = 30.0)]
    rotate: f64,
    /// Runs of each step (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeats: usize,
}

/// The bricks of a survey of about `n` of them (2 : 1.5 : 1 bricks across), each a unit cube
/// rotated by `deg` about z, as world boxes; `field` gives each brick's cost from its centre
/// (in bricks).
fn survey(n: usize, deg: f64, field: impl Fn(f64, f64, f64) -> f64) -> (Region, Vec<CostBox>) {
    let k = (n as f64 / 3.0).cbrt();
    let dims = [
        (2.0 * k).round().max(1.0),
        (1.5 * k).round().max(1.0),
        k.round().max(1.0),
    ]
    .map(|d| d as usize);
    let (s, c) = deg.to_radians().sin_cos();
    let rot = |x: f64, y: f64| (c * x - s * y, s * x + c * y);
    let mut boxes = Vec::with_capacity(dims.iter().product());
    let mut root = Region {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let (x, y, z) = (x as f64, y as f64, z as f64);
                let mut r = Region {
                    lo: [f64::INFINITY, f64::INFINITY, z],
                    hi: [f64::NEG_INFINITY, f64::NEG_INFINITY, z + 1.0],
                };
                for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                    let (wx, wy) = rot(x + dx, y + dy);
                    r.lo[0] = r.lo[0].min(wx);
                    r.hi[0] = r.hi[0].max(wx);
                    r.lo[1] = r.lo[1].min(wy);
                    r.hi[1] = r.hi[1].max(wy);
                }
                for a in 0..3 {
                    root.lo[a] = root.lo[a].min(r.lo[a]);
                    root.hi[a] = root.hi[a].max(r.hi[a]);
                }
                let cost = field(x + 0.5, y + 0.5, z + 0.5);
                boxes.push(CostBox { region: r, cost });
            }
        }
    }
    (root, boxes)
}

/// Median seconds of `repeats` runs of `f` (its last result returned too).
fn timed<T>(repeats: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut times = Vec::new();
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        out = Some(std::hint::black_box(f()));
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    (times[times.len() / 2], out.expect("one run"))
}

fn main() {
    let cli = Cli::parse();
    println!("| boxes | workers | balanced | imbalance_under | reweighted (leaves) | resplit (leaves) | imbalance before / expected |");
    println!("|---|---|---|---|---|---|---|");
    for &n in &cli.boxes {
        // The estimate: denser toward the survey's deep middle.
        let (root, estimate) = survey(n, cli.rotate, |x, y, z| {
            1.0 + 0.5 * (x * 0.05).sin() * (y * 0.07).cos() + 0.02 * z
        });
        // What a view measures: most of the work toward one corner.
        let (_, view) = survey(n, cli.rotate, |x, y, _| 1.0 + 4.0 * (-(x + y) * 0.02).exp());
        let costs = SceneCosts {
            boxes: estimate.clone(),
            planes: [vec![], vec![], vec![]],
            root,
            datasets: vec![],
        };
        for &w in &cli.workers {
            let (t_split, d) = timed(cli.repeats, || {
                Decomposition::balanced(root, &estimate, w, 1, &costs.planes)
            });
            let (t_under, before) = timed(cli.repeats, || d.imbalance_under(&view));
            // Each leaf timed by the view's field.
            let times: Vec<f64> = (0..d.tree.leaves.len())
                .map(|l| {
                    view.iter()
                        .map(|b| b.cost * b.fraction_in(&d.tree.leaves[l]))
                        .sum::<f64>()
                })
                .collect();
            let (t_rw, _) = timed(cli.repeats, || {
                d.reweighted(&estimate, &estimate, &times, 0.5)
            });
            let m = Measurement {
                times: &times,
                work: &[],
            };
            let (t_resplit, r) = timed(cli.repeats, || resplit(&costs, &costs, &d, &m, 0.5, w, 1));
            let expected = r.map_or(f64::NAN, |r| r.expected_imbalance);
            println!(
                "| {} | {w} | {:.1} ms | {:.1} ms | {:.1} ms | {:.1} ms | {before:.3} / {expected:.3} |",
                estimate.len(),
                t_split * 1e3,
                t_under * 1e3,
                t_rw * 1e3,
                t_resplit * 1e3
            );
        }
    }
}
