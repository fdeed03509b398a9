//! `coordinator`: Strata's command-line interface.

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use strata_common::filter::CoarsenFilter;
use strata_common::geo::Affine3;
use strata_common::sample::SampleType;
use strata_common::store::{Compression, Units, VerticalDomain};
use strata_coordinator::builder::{build_store, BuildOptions, BuildReport};
use strata_coordinator::{horizon_text, inspect, overrides, render, segy, source, study, synth};
use tracing::{info, warn};

/// Strata: distributed sort-last rendering of seismic volumes and horizons.
#[derive(Parser)]
#[command(name = "coordinator", version, about, long_about = None)]
struct Cli {
    /// More log output (-v: debug, -vv: trace). RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// No progress bars.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Convert a source file into a multi-resolution page store.
    #[command(subcommand)]
    Ingest(Ingest),
    /// Generate a deterministic synthetic seismic survey (cube, three horizons, scene).
    Synth(SynthArgs),
    /// Summarize a page store; --verify checks every page's checksum.
    Inspect(InspectArgs),
    /// Render a scene to a PNG (8-bit sRGB) and optionally a float RGBA EXR.
    Render(RenderArgs),
    /// Measure what rendering choices cost (`study accuracy`).
    #[command(subcommand)]
    Study(Study),
    /// Join a render run as a worker (what `render` spawns locally; same flags as the
    /// `worker` binary).
    Worker(strata_worker::cli::JoinArgs),
}

#[derive(Args)]
struct RenderArgs {
    /// Scene TOML (e.g. configs/demo.toml).
    scene: PathBuf,
    /// Output PNG.
    #[arg(short, long)]
    output: PathBuf,
    /// Render in this process through the worker engine (the reference image) instead of
    /// over worker processes.
    #[arg(long)]
    in_process: bool,
    /// Worker processes (default: the scene's cluster.workers, else one per core, 2..=8).
    /// Local mode spawns them; with cluster.spawn = false this many are awaited.
    #[arg(long, value_name = "N")]
    workers: Option<usize>,
    /// Override a scene setting, e.g. --set render.cache_mb=64 (repeatable). A relative
    /// path in a value (volume.0.store=...) is taken from the scene file's folder, as in
    /// the file.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    sets: Vec<String>,
    /// Image size, e.g. --size 1920x1080 (overrides render.width and render.height).
    #[arg(long, value_name = "WIDTHxHEIGHT")]
    size: Option<String>,
    /// Also write float RGBA (premultiplied) to this OpenEXR file.
    #[arg(long, value_name = "FILE")]
    exr: Option<PathBuf>,
    /// Write per-worker frame stats and the render summary as JSON lines to this file.
    #[arg(long, value_name = "FILE")]
    stats: Option<PathBuf>,
    /// Render N frames on a circle around the camera's target with the same workers and
    /// resident data; a %05d in -o and --exr numbers the frames (e.g. -o out/frame_%05d.png).
    #[arg(long, value_name = "N", conflicts_with = "path")]
    orbit: Option<u32>,
    /// Render the frames of a camera path (TOML, or JSON by the .json extension: keyframes
    /// of time, eye, target, up, fov_deg; interpolation linear or smooth; fps).
    #[arg(long, value_name = "CAMERA_PATH")]
    path: Option<PathBuf>,
    /// Only frames A to B−1 of the sequence (A..B; A..=B includes B), e.g. to split a
    /// sequence over the jobs of an array. Outputs keep the sequence's frame numbers.
    #[arg(long, value_name = "A..B")]
    frames: Option<String>,
    /// After a sequence, also encode its PNG frames into this MP4 (H.264) with ffmpeg, if
    /// ffmpeg is on the PATH; without it the frames stand alone and a note says so.
    #[arg(long, value_name = "FILE")]
    mp4: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Study {
    /// Render a reference (CPU, step/16, no early termination, level 0 only), then each
    /// accuracy knob alone and in pairs; write report.md, points.csv and error-against-time
    /// plots (PNG, SVG) with the Pareto front and the defaults marked.
    Accuracy(AccuracyArgs),
}

#[derive(Args)]
struct AccuracyArgs {
    /// Scene TOML (e.g. configs/demo.toml).
    scene: PathBuf,
    /// Output folder (created; report.md, points.csv, one KNOB.png and KNOB.svg per knob).
    #[arg(short, long)]
    output: PathBuf,
    /// Image size, e.g. --size 480x270 (overrides render.width and render.height).
    #[arg(long, value_name = "WIDTHxHEIGHT")]
    size: Option<String>,
    /// Override a scene setting for every point and the reference (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    sets: Vec<String>,
    /// Timed frames per point after it converged (the median is reported).
    #[arg(long, default_value_t = 3)]
    frames: usize,
    /// Worker processes of the distributed (wire-precision) points; 0 leaves them out.
    #[arg(long, default_value_t = 2)]
    workers: usize,
    /// Leave out the GPU points (backend gpu, gpu_filter hardware).
    #[arg(long)]
    no_gpu: bool,
}

#[derive(Subcommand)]
enum Ingest {
    /// SEG-Y rev 0/1/2 cube (sample formats 1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16;
    /// pre-stack with --offset or --stack).
    Segy(SegyArgs),
    /// Headerless raw volume, x fastest, then y, then z.
    Raw(RawArgs),
    /// Interpreted horizon from text: `inline crossline z`, `x y inline crossline z`, or a dense grid.
    Horizon(HorizonArgs),
}

#[derive(Args, Clone)]
struct StoreArgs {
    /// Output page store.
    #[arg(short, long)]
    output: PathBuf,
    /// Page size per axis including the border (32, 64 or 128 for volumes; horizons default to 128).
    #[arg(long)]
    brick: Option<u32>,
    /// Border samples per side: 1 for trilinear sampling, 2 when gradients are wanted.
    #[arg(long)]
    border: Option<u32>,
    /// Coarsening filter (default: signed-rms for signed data, mean for unsigned, horizon-mean for horizons).
    #[arg(long, value_enum)]
    filter: Option<FilterArg>,
    /// Per-page compression.
    #[arg(long, value_enum, default_value = "none")]
    compression: CompressionArg,
    /// Working memory for ingest in MiB (pencils and page cache; not counting the OS file cache).
    #[arg(long, default_value_t = 256)]
    memory_mb: usize,
}

#[derive(Copy, Clone, ValueEnum)]
enum FilterArg {
    Mean,
    SignedRms,
    MaxAbs,
    HorizonMean,
}

#[derive(Copy, Clone, ValueEnum)]
enum CompressionArg {
    None,
    Lz4,
}

#[derive(Copy, Clone, ValueEnum)]
enum EndianArg {
    Big,
    Little,
}

#[derive(Args)]
struct SegyArgs {
    /// SEG-Y file.
    file: PathBuf,
    /// Byte order; detected from the binary header when absent.
    #[arg(long, value_enum)]
    endian: Option<EndianArg>,
    /// 1-based byte of the inline number in the trace header (189 by the standard; 9 is common).
    #[arg(long, default_value_t = 189)]
    inline_byte: u32,
    /// 1-based byte of the crossline number in the trace header (193 by the standard; 21 is common).
    #[arg(long, default_value_t = 193)]
    xline_byte: u32,
    /// Time or depth traces; when absent, the --vertical-unit's domain, else what the
    /// textual headers say, else time.
    #[arg(long, value_enum)]
    vertical: Option<VerticalArg>,
    /// Unit of the vertical axis (ms or s for time, m or ft for depth); from the headers
    /// when absent.
    #[arg(long, value_enum)]
    vertical_unit: Option<VerticalUnitArg>,
    /// Sample step along the trace in the vertical unit, overriding the sample-interval
    /// field (which holds the step x 1000: microseconds for ms, thousandths for m or ft).
    #[arg(long, value_name = "STEP")]
    z_step: Option<f64>,
    /// Pre-stack files: ingest only the traces with this offset (trace header byte 37).
    #[arg(
        long,
        value_name = "N",
        allow_negative_numbers = true,
        conflicts_with = "stack"
    )]
    offset: Option<i32>,
    /// Pre-stack files: ingest the mean of the traces of each inline/crossline node.
    #[arg(long)]
    stack: bool,
    #[command(flatten)]
    store: StoreArgs,
}

#[derive(Copy, Clone, ValueEnum)]
enum VerticalArg {
    Time,
    Depth,
}

#[derive(Copy, Clone, ValueEnum)]
enum VerticalUnitArg {
    Ms,
    S,
    M,
    Ft,
}

#[derive(Args)]
struct RawArgs {
    /// Raw file.
    file: PathBuf,
    /// Samples per axis.
    #[arg(long, num_args = 3, value_names = ["NX", "NY", "NZ"], required = true)]
    dims: Vec<u64>,
    /// Sample type.
    #[arg(long, value_parser = ["u8", "i8", "u16", "i16", "f32"])]
    dtype: String,
    /// Samples are big-endian.
    #[arg(long)]
    big_endian: bool,
    /// Sample spacing per axis (world units per sample).
    #[arg(long, num_args = 3, value_names = ["DX", "DY", "DZ"])]
    spacing: Option<Vec<f64>>,
    #[command(flatten)]
    store: StoreArgs,
}

#[derive(Args)]
struct HorizonArgs {
    /// Horizon text file.
    file: PathBuf,
    /// Seismic store of the same survey: use its lateral grid instead of inferring one.
    #[arg(long)]
    survey: Option<PathBuf>,
    /// Column layout; detected from the first data line when `auto`.
    #[arg(long, value_enum, default_value = "auto")]
    format: HorizonFormatArg,
    /// A height value that marks a hole (e.g. -999.25); NaN always does.
    #[arg(long)]
    null: Option<f64>,
    /// Grid format: inline and crossline numbers of the first row and column.
    #[arg(long, num_args = 2, value_names = ["INLINE", "XLINE"])]
    grid_origin: Option<Vec<f64>>,
    /// Grid format: inline and crossline increments per row and column.
    #[arg(long, num_args = 2, value_names = ["DI", "DX"])]
    grid_step: Option<Vec<f64>>,
    /// Unit of the heights (world z); default: the --survey store's vertical unit, else ms.
    #[arg(long)]
    z_unit: Option<String>,
    #[command(flatten)]
    store: StoreArgs,
}

#[derive(Copy, Clone, ValueEnum)]
enum HorizonFormatArg {
    Auto,
    IlXlZ,
    XyIlXlZ,
    Grid,
}

#[derive(Args)]
struct SynthArgs {
    /// Output folder.
    #[arg(short, long)]
    output: PathBuf,
    /// Samples per axis: inlines, crosslines, time samples.
    #[arg(long, num_args = 3, value_names = ["NX", "NY", "NZ"], default_values_t = [400u64, 300, 250])]
    size: Vec<u64>,
    /// Random seed; the same seed and size always give the same survey.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Also write the cube as a SEG-Y file and the horizons as text (for ingest tests).
    #[arg(long)]
    segy: bool,
}

#[derive(Args)]
struct InspectArgs {
    /// Page store.
    store: PathBuf,
    /// Read every page of every level and check its checksum and the level-0 digest.
    #[arg(long)]
    verify: bool,
}

fn progress(quiet: bool, what: &str) -> ProgressBar {
    if quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(0);
    pb.set_style(
        ProgressStyle::with_template(
            "{msg:>14} [{elapsed_precise}] {wide_bar:.cyan/blue} {pos}/{len} pages ({eta})",
        )
        .unwrap(),
    );
    pb.set_message(what.to_string());
    pb
}

fn options(kind_default: BuildOptions, a: &StoreArgs) -> BuildOptions {
    let mut o = kind_default;
    if let Some(b) = a.brick {
        o.page_size = b;
    }
    if let Some(b) = a.border {
        o.border = b;
    }
    if let Some(f) = a.filter {
        o.filter = match f {
            FilterArg::Mean => CoarsenFilter::Mean,
            FilterArg::SignedRms => CoarsenFilter::SignedRms,
            FilterArg::MaxAbs => CoarsenFilter::MaxAbs,
            FilterArg::HorizonMean => CoarsenFilter::HorizonMean,
        };
    }
    o.compression = match a.compression {
        CompressionArg::None => Compression::None,
        CompressionArg::Lz4 => Compression::Lz4,
    };
    o.memory_budget = a.memory_mb.max(16) << 20;
    o
}

fn summarize(out: &Path, r: &BuildReport, secs: f64) {
    let h = r.header.as_ref().expect("a finished build has a header");
    info!(
        store = %out.display(),
        pages = r.pages,
        constant = r.constant_pages,
        empty = r.empty_pages,
        bytes = r.file_bytes,
        seconds = format!("{secs:.2}"),
        "wrote store"
    );
    println!(
        "wrote {}: {} x {} x {} {}, {} levels, {} pages ({} constant, {} empty), {} bytes, digest {:016x}, {:.2} s",
        out.display(),
        h.dims[0],
        h.dims[1],
        h.dims[2],
        h.sample_type.name(),
        h.levels,
        r.pages,
        r.constant_pages,
        r.empty_pages,
        r.file_bytes,
        h.digest,
        secs
    );
}

/// Builds a store with a progress bar and prints the one-line summary.
fn build_and_report(
    src: &dyn source::GridSource,
    out: &Path,
    o: &BuildOptions,
    quiet: bool,
    what: &str,
    t0: std::time::Instant,
) -> Result<()> {
    let pb = progress(quiet, what);
    let r = build_store(src, out, o, &pb)?;
    pb.finish_and_clear();
    summarize(out, &r, t0.elapsed().as_secs_f64());
    if r.moved_off_no_data > 0 {
        if let Some(nd) = o.no_data {
            let step = if nd < o.sample_type.range().1 { 1 } else { -1 };
            warn!(
                samples = r.moved_off_no_data,
                "{}: {} valid samples held the no-data sentinel {nd} (used for the missing traces) and were stored as {} instead",
                out.display(),
                r.moved_off_no_data,
                nd + step as f32
            );
        }
    }
    Ok(())
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Refuses an output that is one of the run's inputs (the same file by another name too):
/// writing it would replace the input.
fn not_an_input(output: &Path, inputs: &[&Path]) -> Result<()> {
    let Ok(out) = std::fs::canonicalize(output) else {
        return Ok(()); // not there yet: no input
    };
    for input in inputs {
        if std::fs::canonicalize(input).is_ok_and(|i| i == out) {
            anyhow::bail!(
                "{}: this is the input {}; writing it would replace it (choose another output)",
                output.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// `path` with its folder resolved (`o.png` and `./o.png` are one file), where the folder
/// exists; else as written.
fn same_file_name(path: &Path) -> PathBuf {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    match (std::fs::canonicalize(parent), path.file_name()) {
        (Ok(dir), Some(name)) => dir.join(name),
        _ => path.to_path_buf(),
    }
}

/// Checks, before any work, that the folder an output goes to exists.
fn folder_exists(output: &Path, what: &str) -> Result<()> {
    let parent = match output.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    anyhow::ensure!(
        parent.is_dir(),
        "{}: the folder {} of the {what} does not exist",
        output.display(),
        parent.display()
    );
    Ok(())
}

/// `--mp4`: encodes the sequence's frames if asked, or says why it could not.
fn mp4_step(opts: &render::RenderOptions, mp4: Option<&Path>) -> Result<()> {
    use strata_coordinator::sequence::Mp4;
    let Some(mp4) = mp4 else {
        return Ok(());
    };
    match render::write_mp4(opts, mp4)? {
        Mp4::Written => println!("wrote {}", mp4.display()),
        Mp4::NoFfmpeg => eprintln!(
            "note: ffmpeg is not on the PATH, so no {} was written; the PNG frames are complete",
            mp4.display()
        ),
    }
    Ok(())
}

fn run(cli: Cli) -> Result<()> {
    let t0 = std::time::Instant::now();
    match cli.command {
        Command::Ingest(Ingest::Raw(a)) => {
            let dtype = SampleType::parse(&a.dtype).expect("clap restricts --dtype");
            let dims = [a.dims[0], a.dims[1], a.dims[2]];
            not_an_input(&a.store.output, &[&a.file])?;
            let src = source::RawSource::open(&a.file, dims, dtype, a.big_endian)?;
            let mut o = options(BuildOptions::volume(&file_name(&a.file), dtype), &a.store);
            if let Some(s) = &a.spacing {
                o.transform = Affine3::scale_offset([s[0], s[1], s[2]], [0.0; 3]);
            }
            o.source = format!(
                "raw {} ({} {:?}, {})",
                a.file.display(),
                dtype.name(),
                dims,
                if a.big_endian {
                    "big-endian"
                } else {
                    "little-endian"
                }
            );
            build_and_report(&src, &a.store.output, &o, cli.quiet, "raw", t0)?;
        }
        Command::Ingest(Ingest::Segy(a)) => {
            let opts = segy::SegyOptions {
                endian: a.endian.map(|e| match e {
                    EndianArg::Big => segy::Endian::Big,
                    EndianArg::Little => segy::Endian::Little,
                }),
                inline_byte: a.inline_byte,
                xline_byte: a.xline_byte,
                offset: a.offset,
                stack: a.stack,
                vertical: a.vertical.map(|v| match v {
                    VerticalArg::Time => segy::VerticalDomain::Time,
                    VerticalArg::Depth => segy::VerticalDomain::Depth,
                }),
                vertical_unit: a.vertical_unit.map(|u| match u {
                    VerticalUnitArg::Ms => segy::VerticalUnit::Ms,
                    VerticalUnitArg::S => segy::VerticalUnit::S,
                    VerticalUnitArg::M => segy::VerticalUnit::M,
                    VerticalUnitArg::Ft => segy::VerticalUnit::Ft,
                }),
                z_step: a.z_step,
            };
            not_an_input(&a.store.output, &[&a.file])?;
            let vol = segy::open(&a.file, &opts)?;
            let info = vol.info();
            for w in &info.warnings {
                warn!("{}: {w}", a.file.display());
            }
            let v = &info.vertical;
            info!(
                domain = v.domain.name(),
                unit = v.unit.name(),
                start = v.start,
                step = v.step,
                domain_from = %v.domain_from,
                unit_from = %v.unit_from,
                "vertical axis"
            );
            let mut o = options(
                BuildOptions::volume(&file_name(&a.file), info.sample_type),
                &a.store,
            );
            if info.missing_traces > 0 && info.sample_type != SampleType::F32 {
                o.no_data = Some(info.sample_type.range().0);
            }
            let (z0, dz) = vol.z_axis();
            o.transform = Affine3::from_lateral(&info.survey.to_world, dz, z0);
            o.units = Units {
                lateral: "m".into(),
                vertical: v.unit.name().into(),
            };
            o.vertical_domain = Some(v.domain);
            o.survey = Some(info.survey);
            let text: String = info
                .text_header
                .lines()
                .filter(|l| !l.trim().is_empty())
                .take(40)
                .collect::<Vec<_>>()
                .join("\n");
            let traces = match (info.offset, info.stacked) {
                (Some(o), _) => format!(", offset {o} only"),
                (None, true) => format!(", stack of up to {} traces per node", info.max_fold),
                (None, false) => String::new(),
            };
            o.source = format!(
                "SEG-Y {} (format {}, rev {}.{}{traces}; {} in {}, {})\n{}",
                a.file.display(),
                info.format_code,
                info.revision.0,
                info.revision.1,
                v.domain.name(),
                v.unit.name(),
                v.domain_from,
                text
            );
            if let Some(f) = &info.fit {
                info!(
                    rms_m = f.rms_residual,
                    max_m = f.max_residual,
                    "fitted inline/crossline -> x/y transform"
                );
            }
            build_and_report(&vol, &a.store.output, &o, cli.quiet, "SEG-Y", t0)?;
        }
        Command::Ingest(Ingest::Horizon(a)) => {
            let inputs: Vec<&Path> = std::iter::once(a.file.as_path())
                .chain(a.survey.as_deref())
                .collect();
            not_an_input(&a.store.output, &inputs)?;
            let survey_store = match &a.survey {
                Some(p) => Some(inspect::open_store(p)?),
                None => None,
            };
            let survey = match (&a.survey, &survey_store) {
                (Some(p), Some(s)) => Some(
                    s.header()
                        .survey
                        .with_context(|| format!("{}: store has no survey grid", p.display()))?,
                ),
                _ => None,
            };
            // Heights share the survey cube's vertical axis unless told otherwise.
            let (z_unit, z_domain) = match (&a.z_unit, &survey_store) {
                // A unit that names a domain records it.
                (Some(u), _) => (
                    u.clone(),
                    match u.as_str() {
                        "ms" | "s" => Some(VerticalDomain::Time),
                        "m" | "ft" => Some(VerticalDomain::Depth),
                        _ => None,
                    },
                ),
                (None, Some(s)) => (
                    s.header().units.vertical.clone(),
                    s.header().vertical_domain,
                ),
                (None, None) => ("ms".to_string(), None),
            };
            let mut po = horizon_text::HorizonParseOptions {
                format: match a.format {
                    HorizonFormatArg::Auto => horizon_text::HorizonFormat::Auto,
                    HorizonFormatArg::IlXlZ => horizon_text::HorizonFormat::IlXlZ,
                    HorizonFormatArg::XyIlXlZ => horizon_text::HorizonFormat::XyIlXlZ,
                    HorizonFormatArg::Grid => horizon_text::HorizonFormat::Grid,
                },
                null_value: a.null,
                survey,
                ..Default::default()
            };
            if let Some(g) = &a.grid_origin {
                po.grid_origin = (g[0], g[1]);
            }
            if let Some(g) = &a.grid_step {
                po.grid_step = (g[0], g[1]);
            }
            let grid = horizon_text::parse_horizon(&a.file, &po)?;
            for w in &grid.warnings {
                warn!("{}: {w}", a.file.display());
            }
            if let Some(f) = &grid.fit {
                println!(
                    "fitted inline/crossline -> x/y: rms residual {:.4} m, max {:.4} m",
                    f.rms_residual, f.max_residual
                );
            }
            println!(
                "{} nodes read, {} holes, {} dropped outside the survey grid",
                grid.nodes_read, grid.holes, grid.dropped
            );
            let s = grid.survey;
            let mut o = options(BuildOptions::horizon(&file_name(&a.file)), &a.store);
            if a.store.brick.is_none() {
                o.page_size = 128;
            }
            o.transform = Affine3::from_lateral(&s.to_world, 1.0, 0.0);
            o.units = Units {
                lateral: "m".into(),
                vertical: z_unit,
            };
            o.vertical_domain = z_domain;
            o.survey = Some(s);
            o.source = format!("horizon text {}", a.file.display());
            let src = source::MemorySource {
                dims: [s.n_inline, s.n_xline, 1],
                data: grid.heights,
            };
            build_and_report(&src, &a.store.output, &o, cli.quiet, "horizon", t0)?;
        }
        Command::Synth(a) => {
            let pb = progress(cli.quiet, "synth");
            let out = synth::synth(
                &a.output,
                [a.size[0], a.size[1], a.size[2]],
                a.seed,
                a.segy,
                &pb,
            )?;
            pb.finish_and_clear();
            summarize(&out.volume, &out.volume_report, t0.elapsed().as_secs_f64());
            for h in &out.horizons {
                println!("wrote {}", h.display());
            }
            if let Some(s) = &out.segy {
                println!("wrote {}", s.display());
            }
            println!("wrote {}", out.scene.display());
        }
        Command::Render(a) => {
            let size = a.size.as_deref().map(overrides::parse_size).transpose()?;
            let opts = render::RenderOptions {
                scene: a.scene.clone(),
                output: a.output.clone(),
                exr: a.exr.clone(),
                sets: a.sets.clone(),
                size,
                workers: a.workers,
                orbit: a.orbit,
                path: a.path.clone(),
                frames: a.frames.as_deref().map(render::parse_frames).transpose()?,
                mp4: a.mp4.is_some(),
            };
            anyhow::ensure!(
                a.mp4.is_none() || a.orbit.is_some() || a.path.is_some(),
                "--mp4 needs a sequence (--orbit N or --path FILE)"
            );
            // Outputs are checked before the render, not found wanting after it.
            let inputs: Vec<&Path> = std::iter::once(a.scene.as_path())
                .chain(a.path.as_deref())
                .collect();
            let outputs = [
                (Some(&a.output), "image (-o)"),
                (a.exr.as_ref(), "EXR image (--exr)"),
                (a.stats.as_ref(), "stats (--stats)"),
                (a.mp4.as_ref(), "video (--mp4)"),
            ];
            // Two outputs that are one file (however spelt): the later would silently
            // replace the first.
            for (i, (x, xw)) in outputs.iter().enumerate() {
                for (y, yw) in &outputs[i + 1..] {
                    if let (Some(x), Some(y)) = (x, y) {
                        anyhow::ensure!(
                            same_file_name(x) != same_file_name(y),
                            "{}: the {xw} and the {yw} are the same file",
                            x.display()
                        );
                    }
                }
            }
            // Every check first, then the sequence folders: a refused command makes none.
            let sequence = a.orbit.is_some() || a.path.is_some();
            // A sequence's numbered frames: another output that is one of them would be
            // replaced by a frame, or replace one (an --mp4 written over a frame it encodes).
            // The per-frame patterns: only the images (the first two outputs) are written per
            // frame; --stats and --mp4 are one file each.
            let patterns: Vec<(&PathBuf, &str)> = outputs[..2]
                .iter()
                .filter(|_| sequence)
                .filter_map(|&(o, w)| {
                    o.filter(|o| strata_coordinator::sequence::is_numbered(o).unwrap_or(false))
                        .map(|o| (o, w))
                })
                .collect();
            for &(x, xw) in &patterns {
                for (y, yw) in &outputs {
                    if let Some(y) = y {
                        anyhow::ensure!(
                            !strata_coordinator::sequence::is_frame_of(
                                &same_file_name(x),
                                &same_file_name(y)
                            ),
                            "{}: the {yw} is one of the frames of the {xw} ({})",
                            y.display(),
                            x.display()
                        );
                    }
                }
            }
            render::check_sequence(&opts)?;
            let mut folders = Vec::new();
            // Outputs in the folder the frames' pattern makes are checked once it is known.
            let mut later = Vec::new();
            for (out, what) in outputs {
                if let Some(out) = out {
                    anyhow::ensure!(
                        !out.is_dir(),
                        "{}: the {what} is a folder (expected a file name)",
                        out.display()
                    );
                    not_an_input(out, &inputs)?;
                    // A sequence's frames go to a folder of their own, made here: the
                    // pattern's folder as the frames name it (`%%` is `%` there), so the
                    // frame number must be in the file name.
                    if patterns.iter().any(|&(p, _)| std::ptr::eq(p, out)) {
                        let name_numbered = out.file_name().is_some_and(|n| {
                            strata_coordinator::sequence::is_numbered(Path::new(n)).unwrap_or(false)
                        });
                        anyhow::ensure!(
                            name_numbered,
                            "{}: the frame-number pattern of the {what} must be in the file name, not in a folder",
                            out.display()
                        );
                        let first = strata_coordinator::sequence::numbered(out, 0)?;
                        match first.parent().filter(|p| !p.as_os_str().is_empty()) {
                            Some(dir) => folders.push((out, dir.to_path_buf())),
                            None => folder_exists(out, what)?,
                        }
                    } else {
                        later.push((out, what));
                    }
                }
            }
            // A single-file output (--stats, --mp4) may go into the folder made for the
            // frames.
            for (out, what) in later {
                let made = folders.iter().any(|(_, dir)| {
                    out.parent()
                        .is_some_and(|p| same_file_name(p) == same_file_name(dir))
                });
                if !made {
                    folder_exists(out, what)?;
                }
            }
            for (out, dir) in folders {
                std::fs::create_dir_all(&dir).with_context(|| {
                    format!(
                        "{}: cannot create the folder {}",
                        out.display(),
                        dir.display()
                    )
                })?;
            }
            if a.in_process && a.workers.is_some() {
                warn!("--workers is ignored with --in-process (one process renders)");
            }
            let pb = progress(cli.quiet, "synth");
            let s = if a.in_process {
                render::render_in_process(&opts, &pb)
            } else {
                render::render_distributed(&opts, &pb)
            };
            pb.finish_and_clear();
            let s = s?;
            if s.workers > 0 {
                println!(
                    "{} workers, {}: compositing {:.1} ms, {:.1} MiB exchanged, {:.1} MiB gathered; transport: {}",
                    s.workers,
                    s.algorithm.as_deref().unwrap_or("?"),
                    s.composite_seconds * 1e3,
                    s.exchange_bytes as f64 / (1 << 20) as f64,
                    s.gather_bytes as f64 / (1 << 20) as f64,
                    s.transport.as_ref().map_or("?".into(), |t| t.describe())
                );
            }
            for j in &s.joined_workers {
                println!(
                    "{} joined the running sequence at frame {} and took load after a set-up of {:.1} s on {} workers",
                    j.worker,
                    j.frame,
                    j.setup_s,
                    j.assignment.len()
                );
            }
            for l in &s.lost_workers {
                let what = if l.phase == "set-up" {
                    "during set-up, and set the run up"
                } else {
                    "and re-rendered"
                };
                println!(
                    "lost {} after {:.1} s {what} without it in {:.1} s on {} workers: {}",
                    l.worker,
                    l.detected_after_s,
                    l.recovery_s,
                    l.assignment.len(),
                    l.reason
                );
            }
            if s.sequence.is_empty() {
                println!(
                    "nothing to render: all {} frame(s) of the range exist complete",
                    s.skipped
                );
                // The stats still say so (a script reads them after every run).
                if let Some(p) = &a.stats {
                    synth::write_atomically(p, s.json_lines()?.as_bytes())?;
                }
                mp4_step(&opts, a.mp4.as_deref())?;
                return Ok(());
            }
            println!(
                "rendered {}x{} in {:.2} s: {} after {} round(s); last frame's casts {:.3} s, {} samples ({:.1} M samples/s)",
                s.width,
                s.height,
                s.seconds,
                s.outcome,
                s.rounds,
                s.last_frame_seconds + s.first_pass_seconds,
                s.samples,
                // Every cast the samples count over its time (distributed: the occlusion
                // first pass's too).
                s.samples as f64 / (s.last_frame_seconds + s.first_pass_seconds).max(1e-9) / 1e6
            );
            println!("backend: {}", s.backend);
            println!("effects: {}; code path: {}", s.effects, s.variant);
            println!(
                "cast {:.2} s, load {:.2} s; pages read {} ({:.1} MiB), cache hit rate {:.1}%",
                s.cast_seconds,
                s.load_seconds,
                s.pages_read,
                s.bytes_read as f64 / (1 << 20) as f64,
                100.0 * s.cache_hit_rate
            );
            if s.skipped > 0 {
                println!(
                    "{} frame(s) skipped: their outputs exist and are complete",
                    s.skipped
                );
            }
            if s.sequence.len() > 1 || a.orbit.is_some() || a.path.is_some() {
                let secs: Vec<f64> = s.sequence.iter().map(|f| f.seconds).collect();
                if let [first, rest @ ..] = &secs[..] {
                    if rest.is_empty() {
                        println!("1 frame: {first:.2} s");
                    } else {
                        let mean = rest.iter().sum::<f64>() / rest.len() as f64;
                        println!(
                            "{} frames: first {first:.2} s (cold), then {mean:.2} s per frame on average ({:.2} frames/s)",
                            secs.len(),
                            1.0 / mean.max(1e-9)
                        );
                    }
                }
                let (first, last) = (&s.sequence[0], &s.sequence[s.sequence.len() - 1]);
                match s.wall {
                    // Only tiles: name the first frame's first tile and the last's last.
                    Some([c, r]) if !s.wall_preview => {
                        let last_png =
                            strata_coordinator::sequence::numbered(&a.output, last.frame)?;
                        println!(
                            "wrote {c}x{r} wall tiles per frame, {} … {}",
                            first.output,
                            strata_common::wall::tile_path(&last_png, c - 1, r - 1).display()
                        );
                    }
                    _ => println!("wrote {} … {}", first.output, last.output),
                }
            } else if let Some([c, r]) = s.wall {
                use strata_common::wall::tile_path;
                for o in std::iter::once(&a.output).chain(&a.exr) {
                    println!(
                        "wrote {c}x{r} wall tiles {} … {}",
                        tile_path(o, 0, 0).display(),
                        tile_path(o, c - 1, r - 1).display()
                    );
                }
                if s.wall_preview {
                    println!("wrote the preview mosaic {}", a.output.display());
                }
            } else {
                println!("wrote {}", a.output.display());
                if let Some(e) = &a.exr {
                    println!("wrote {}", e.display());
                }
            }
            if let Some(p) = &a.stats {
                synth::write_atomically(p, s.json_lines()?.as_bytes())?;
            }
            mp4_step(&opts, a.mp4.as_deref())?;
        }
        Command::Worker(a) => {
            strata_worker::cli::join(a)?;
        }
        Command::Study(Study::Accuracy(a)) => {
            anyhow::ensure!(
                (1..=1000).contains(&a.frames),
                "--frames must lie in 1..=1000, got {}",
                a.frames
            );
            anyhow::ensure!(
                a.workers != 1 && a.workers <= 256,
                "--workers must be 0 (none) or lie in 2..=256, got {}",
                a.workers
            );
            let opts = study::StudyOptions {
                scene: a.scene.clone(),
                out: a.output.clone(),
                size: a.size.as_deref().map(overrides::parse_size).transpose()?,
                sets: a.sets.clone(),
                frames: a.frames,
                workers: a.workers,
                gpu: !a.no_gpu,
            };
            let pb = progress(cli.quiet, "study");
            let points = study::run(&opts, &pb)?;
            pb.finish_and_clear();
            println!(
                "{} points; wrote {}",
                points.len(),
                a.output.join("report.md").display()
            );
        }
        Command::Inspect(a) => {
            let pb = progress(cli.quiet, "inspect");
            let r = inspect::inspect(&a.store, a.verify, &pb)?;
            pb.finish_and_clear();
            print!("{}", r.text);
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    strata_worker::node::retain_freed_memory();
    let level = match cli.verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .init();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    /// clap's own consistency checks of every command, flag and default (they otherwise
    /// run only when a command is parsed).
    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        super::Cli::command().debug_assert();
    }
}
