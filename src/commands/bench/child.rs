//! Benchmarks of the table that run in a child `kfmap bench` process of their own.

use std::process::Command;

use anyhow::{Context, bail};

/// Runs `kfmap bench ARGS --json` as a child process and returns its JSON.
pub(super) fn child_bench(args: &[&str]) -> anyhow::Result<serde_json::Value> {
    let out = Command::new(std::env::current_exe()?)
        .arg("bench")
        .args(args)
        .arg("--json")
        .output()
        .with_context(|| format!("run kfmap bench {}", args.join(" ")))?;
    if !out.status.success() {
        bail!(
            "kfmap bench {} failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(serde_json::from_slice(&out.stdout)?)
}
