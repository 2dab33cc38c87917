//! Benchmarks of the table that run in a child `kfmap bench` process of their own.

use std::process::Command;

use anyhow::{Context, bail};

/// Runs `kfmap bench ARGS --json` as a child process and returns its JSON.
pub(super) fn child_bench(args: &[&str]) -> anyhow::Result<serde_json::Value> {
    let mut command = Command::new(std::env::current_exe()?);
    command.arg("bench").args(args);
    run_json(command, &format!("kfmap bench {}", args.join(" ")))
}

/// Runs `command --json` (a `kfmap bench` invocation, possibly wrapped) and returns the
/// JSON it printed; `what` names it in errors.
pub(super) fn run_json(mut command: Command, what: &str) -> anyhow::Result<serde_json::Value> {
    let out = command
        .arg("--json")
        .output()
        .with_context(|| format!("run {what}"))?;
    if !out.status.success() {
        bail!("{what} failed: {}", String::from_utf8_lossy(&out.stderr));
    }
    Ok(serde_json::from_slice(&out.stdout)?)
}
