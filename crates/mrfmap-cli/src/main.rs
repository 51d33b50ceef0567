//! The `mrfmap` command: a thin layer over the `mrfmap` library.
//!
//! Each subcommand lives in `commands/`; this file parses arguments, sets up logging and
//! threads, and turns errors into one clear line and a non-zero exit code.

mod commands;
mod progress;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "mrfmap", version, about = "Probabilistic 3D occupancy maps from depth cameras")]
struct Cli {
    /// No progress bars and no log lines below warnings.
    #[arg(long, short, global = true)]
    quiet: bool,
    /// Debug log lines of mrfmap too: e.g. the tiles and rays each sweep of MRF inference
    /// traced (RUST_LOG, when set, decides instead).
    #[arg(long, short, global = true, conflicts_with = "quiet")]
    verbose: bool,
    /// Worker threads (default: all cores; at most 1024). With two or more, `build` reads
    /// the next frame on a thread of its own while it integrates this one.
    #[arg(long, global = true, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// Memory a command may plan to use, e.g. 8G (default: MRFMAP_MAX_MEMORY, else three
    /// quarters of physical memory). Work whose estimate is larger is refused before it starts.
    #[arg(long, global = true, value_parser = |s: &str| mrfmap::limits::parse_bytes(s).map_err(|e| e.to_string()))]
    max_memory: Option<u64>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Build a map from a dataset, a laser log, or a ROS 2 (MCAP, .db3) or ROS 1 bag.
    Build(commands::build::Args),
    /// Look into a ROS 2 or ROS 1 bag: `bag info BAG`.
    #[cfg(feature = "bags")]
    Bag(commands::bag::Args),
    /// Write a ROS 2 or ROS 1 bag's posed depth images as a TUM-layout dataset.
    #[cfg(feature = "bags")]
    ExportDataset(commands::bag::ExportArgs),
    /// Learn a per-patch noise model (noise.toml) from measured and true depth images.
    Calibrate(commands::calibrate::Args),
    /// Look at a noise model: `noise plot noise.toml -o curves.png`.
    Noise(commands::noise::Args),
    /// Make a noise-free dataset noisy, as a depth camera would read it (Kinect model or a
    /// noise.toml); the clean depth becomes gt_depth/.
    AddNoise(commands::noise::AddArgs),
    /// Export a map to PLY, OctoMap (.bt, .ot) or a Foxglove scene (.mcap).
    Export(commands::export::Args),
    /// A PNG picture of a map from a viewpoint, or a slice of it.
    View(commands::view::Args),
    /// Describe a map file.
    Info(commands::info::Args),
    /// Ask a map what a planner asks: occupancy at points, is a path or a box free (`--json`).
    Query(commands::query::Args),
    /// Keep only the voxels in a box.
    Crop(commands::ops::BoxArgs),
    /// Make the voxels in a box unknown.
    Clear(commands::ops::BoxArgs),
    /// Combine two maps of one engine and resolution.
    Merge(commands::ops::MergeArgs),
    /// Voxels whose state (unknown, free, occupied) differs between two maps.
    Diff(commands::ops::DiffArgs),
    /// The 2D occupancy grid of a height slab (ROS map_server PGM + YAML).
    Project(commands::ops::ProjectArgs),
    /// Render an analytic scene file to a dataset.
    Simulate(commands::simulate::Args),
    /// Simulate the bundled room scene, build maps with every engine, export PLY.
    Demo(commands::demo::Args),
    /// Score a map: accuracy on held-out views of a dataset, or metrics against a scene.
    Eval(commands::eval::Args),
    /// Leave-one-out accuracy: build without each view, score on it.
    Loo(commands::loo::Args),
    /// Engines and resolutions side by side: a Markdown report with tables and pictures.
    Compare(commands::compare::Args),
    /// Time and memory against resolution, image size and MRF keyframes: tables and plots.
    Scaling(commands::scaling::Args),
    /// Regenerate a paper's experiment (`experiment crm-2d -o DIR`).
    Experiment(commands::experiment::Args),
    /// Time map building per frame at several resolutions (release builds only make sense).
    Bench(commands::bench::Args),
    /// Print a shell completion script: e.g. `mrfmap completions bash > ~/.local/share/bash-completion/completions/mrfmap`.
    Completions {
        /// The shell: bash, zsh, fish, elvish or powershell.
        shell: clap_complete::Shell,
    },
}

fn main() {
    // `mrfmap info MAP | head`: printing to a closed pipe makes `println!` panic; a reader
    // that stopped reading is not an error, so end quietly as a C tool killed by SIGPIPE would.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let text = info.payload().downcast_ref::<String>().map(String::as_str);
        if text.is_some_and(|t| t.contains("Broken pipe")) {
            std::process::exit(141);
        }
        default_hook(info)
    }));
    // Argument errors exit 1 with the same prefix as every other error (clap's own exit code
    // is 2); help and version still print to stdout and exit 0.
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if e.use_stderr() => {
            let text = e.render().to_string();
            eprintln!("mrfmap: {}", text.trim_end());
            std::process::exit(1);
        }
        Err(e) => e.exit(),
    };
    let default_level = match (cli.quiet, cli.verbose) {
        (true, _) => "warn",
        (_, true) => "info,mrfmap=debug",
        _ => "info",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
    // Colour only for a terminal, and never with NO_COLOR set (https://no-color.org).
    use std::io::IsTerminal;
    let ansi = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_ansi(ansi)
        .init();
    progress::set_quiet(cli.quiet);

    let result = (|| {
        match cli.max_memory {
            Some(bytes) => mrfmap::limits::set_max_memory(bytes),
            // Checked here, so that a typo is an error rather than the default limit.
            None => {
                mrfmap::limits::env_max_memory()?;
            }
        }
        // (Before any thread is started: a thread takes its arena at its first allocation.)
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        limit_malloc_arenas(cli.threads.map_or(cores, |n| n as usize));
        // This thread is one of the pool's (the rest are started for it): a command's parallel
        // steps then start where they are called, and each of a frame's dozen steps wakes one
        // other thread instead of handing itself to the pool while this one sleeps (two
        // threads: 0.92-0.97x the integration time of a log-odds build, one thread 0.89-0.99x;
        // BENCHMARKS.md, session 40). What this thread waits on outside rayon (the frame read
        // ahead, a bag's reading threads) never needs the pool to finish. (0 threads: rayon's
        // default, RAYON_NUM_THREADS or one per core.)
        let threads = cli.threads.map_or(0, |n| n as usize);
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .use_current_thread()
            // (Known to `placement` from the first frame: BENCHMARKS.md, session 48.)
            .start_handler(|_| mrfmap::placement::register_thread())
            .build_global()?;
        match cli.command {
            Command::Build(a) => commands::build::run(a),
            #[cfg(feature = "bags")]
            Command::Bag(a) => commands::bag::run(a),
            #[cfg(feature = "bags")]
            Command::ExportDataset(a) => commands::bag::export_dataset(a),
            Command::Calibrate(a) => commands::calibrate::run(a),
            Command::Noise(a) => commands::noise::run(a),
            Command::AddNoise(a) => commands::noise::add(a),
            Command::Export(a) => commands::export::run(a),
            Command::View(a) => commands::view::run(a),
            Command::Info(a) => commands::info::run(a),
            Command::Query(a) => commands::query::run(a),
            Command::Crop(a) => commands::ops::crop(a),
            Command::Clear(a) => commands::ops::clear(a),
            Command::Merge(a) => commands::ops::merge(a),
            Command::Diff(a) => commands::ops::diff(a),
            Command::Project(a) => commands::ops::project(a),
            Command::Simulate(a) => commands::simulate::run(a),
            Command::Demo(a) => commands::demo::run(a),
            Command::Eval(a) => commands::eval::run(a),
            Command::Loo(a) => commands::loo::run(a),
            Command::Compare(a) => commands::compare::run(a),
            Command::Scaling(a) => commands::scaling::run(a),
            Command::Experiment(a) => commands::experiment::run(a),
            Command::Bench(a) => commands::bench::run(a),
            Command::Completions { shell } => {
                use clap::CommandFactory;
                clap_complete::generate(shell, &mut Cli::command(), "mrfmap", &mut std::io::stdout());
                Ok(())
            }
        }
    })();
    if let Err(e) = result {
        eprintln!("mrfmap: error: {e:#}");
        std::process::exit(1);
    }
}

/// glibc's malloc gives each thread that allocates an arena of its own, up to eight per core,
/// and memory freed into one arena is not reused by another: a build on two threads, with the
/// next frame read on a third, peaked 1.5-2 MB higher (5% of a small map's process) than with
/// one arena per computing thread, at the same speed (BENCHMARKS.md, session 31). So this
/// process keeps one arena per thread it computes on. On one thread that is the main arena
/// alone: a second one (the pool's worker allocates, the main thread waits) grew a page or so
/// at a time, 3,000-4,600 `mprotect` calls a build at 0.02 m, and it cost 3-4% of the
/// integration time and 1.3-2.3 MB of peak memory (BENCHMARKS.md, session 34).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn limit_malloc_arenas(threads: usize) {
    use std::ffi::c_int;
    unsafe extern "C" {
        fn mallopt(param: c_int, value: c_int) -> c_int;
    }
    const M_ARENA_MAX: c_int = -8; // glibc's malloc.h
    // SAFETY: `mallopt` sets one of the allocator's parameters and is safe to call at any
    // time (glibc takes its lock); an arena limit only decides where later allocations go.
    unsafe {
        mallopt(M_ARENA_MAX, threads.clamp(1, 1024) as c_int);
    }
}

/// (Other allocators share their arenas on their own terms.)
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn limit_malloc_arenas(_threads: usize) {}
