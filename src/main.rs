//! `kfmap`: the command-line front end. Each subcommand lives in `commands/`; the work
//! itself is in the `kfmap-geometry`, `kfmap-map`, `kfmap-graph`, `kfmap-service` and
//! `kfmap-client` crates.

mod commands;

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use tracing_subscriber::util::SubscriberInitExt;

/// kfmap: a keyframe point-cloud map server for LiDAR localization.
#[derive(Parser)]
#[command(name = "kfmap", version, about, long_about = None, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    Bake(commands::bake::Args),
    Bench(kfmap_bench::Args),
    Inspect(commands::inspect::Args),
    InspectBag(commands::inspect_bag::Args),
    InspectCloud(commands::inspect_cloud::Args),
    OptimizeGraph(commands::optimize_graph::Args),
    Plot(commands::plot::Args),
    Register(commands::register::Args),
    Simulate(commands::simulate::Args),
    Demo(commands::demo::Args),
    Gateway(commands::gateway::Args),
    Gravity(commands::gravity::Args),
    // Boxed: its many tracker flags make it the largest command by far.
    Localize(Box<commands::localize::Args>),
    Query(commands::query::Args),
    Relocalize(commands::relocalize::Args),
    Serve(commands::serve::Args),
    Status(commands::status::Args),
}

fn main() -> ExitCode {
    let started = std::time::Instant::now(); // Cold-start figures count from here.
    // KFMAP_LOG=debug|info|warn|error (default info); debug logs every server request.
    let level = std::env::var("KFMAP_LOG")
        .ok()
        .and_then(|l| l.parse().ok())
        .unwrap_or(tracing::Level::INFO);
    // Zenoh (remote clients, the gateway) says what it does at info level: its own
    // lines only from warnings, unless KFMAP_LOG asks for debug.
    // (tracing orders levels by verbosity: TRACE > DEBUG > INFO > WARN > ERROR.)
    let zenoh_level = if level >= tracing::Level::DEBUG {
        level
    } else {
        level.min(tracing::Level::WARN)
    };
    let filter = tracing_subscriber::filter::Targets::new()
        .with_default(level)
        .with_target("zenoh", zenoh_level);
    tracing_subscriber::layer::SubscriberExt::with(
        tracing_subscriber::fmt()
            .with_writer(std::io::stderr)
            // Colour codes only for a person at a terminal, never in a log file or pipe.
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            // A closed stderr must not panic a server: its own report of the failed write
            // would go to the same stderr.
            .log_internal_errors(false)
            .with_max_level(level)
            .finish(),
        filter,
    )
    .init();
    // iceoryx2's own warnings, one line per kind of event with a count, never per event.
    kfmap_protocol::log_limit::install();
    // A closed output pipe (`kfmap ... | head`) ends the process quietly (status 141)
    // instead of a panic on the failed print.
    set_sigpipe(libc::SIG_DFL);
    let cli = Cli::parse(); // Usage errors exit with code 2 and a message from clap.
    if matches!(
        cli.command,
        Command::Serve(_) | Command::Gateway(_) | Command::Demo(_) | Command::Bench(_)
    ) {
        // These own a server, child processes or shared memory to clean up: a signal
        // death would skip that, so a broken pipe stays an I/O error here.
        set_sigpipe(libc::SIG_IGN);
    }
    let result = match cli.command {
        Command::Bake(args) => commands::bake::run(args),
        Command::Bench(args) => kfmap_bench::run(args, started),
        Command::Inspect(args) => commands::inspect::run(args),
        Command::InspectBag(args) => commands::inspect_bag::run(args),
        Command::InspectCloud(args) => commands::inspect_cloud::run(args),
        Command::OptimizeGraph(args) => commands::optimize_graph::run(args),
        Command::Plot(args) => commands::plot::run(args),
        Command::Register(args) => commands::register::run(args),
        Command::Simulate(args) => commands::simulate::run(args),
        Command::Demo(args) => commands::demo::run(args),
        Command::Gateway(args) => commands::gateway::run(args),
        Command::Gravity(args) => commands::gravity::run(args),
        Command::Localize(args) => commands::localize::run(*args),
        Command::Query(args) => commands::query::run(args),
        Command::Relocalize(args) => commands::relocalize::run(args),
        Command::Serve(args) => commands::serve::run(args),
        Command::Status(args) => commands::status::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::from(2)
        }
    }
}

/// Sets what SIGPIPE does to this process.
fn set_sigpipe(action: libc::sighandler_t) {
    // SAFETY: setting a signal's disposition to SIG_DFL or SIG_IGN installs no handler
    // code; it is done before any thread is spawned.
    unsafe {
        libc::signal(libc::SIGPIPE, action);
    }
}
