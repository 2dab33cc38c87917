//! A `kfmap serve` child process, for the commands that run a server of their own
//! (demo, benchmarks).

use std::ffi::OsStr;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};

use anyhow::{Context, bail};
use kfmap_bake::source::Source;
use kfmap_protocol::transport::{iceoryx_config, remove_prefix_files};

/// The server child: stopped, and every iceoryx2 file of its prefix removed, on drop.
pub struct ServerChild {
    child: Child,
    /// Its iceoryx2 prefix, this process's own.
    pub prefix: String,
    /// The map name it serves.
    pub name: String,
    /// The line it printed when ready.
    pub ready: String,
}

impl ServerChild {
    /// Starts `kfmap serve` on `map` as `name` under `prefix`, with `extra` arguments,
    /// and waits until it answers.
    pub fn start(map: &Path, name: &str, prefix: &str, extra: &[&str]) -> anyhow::Result<Self> {
        let child = Command::new(std::env::current_exe()?)
            .args(["serve", "--map"])
            .arg(map)
            .args(["--map-name", name, "--iceoryx-prefix", prefix])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .context("start kfmap serve")?;
        // Owned from here: any failure below stops it and removes its shared memory.
        let mut server = Self {
            child,
            prefix: prefix.to_string(),
            name: name.to_string(),
            ready: String::new(),
        };
        let stdout = server.child.stdout.take().context("server stdout")?;
        // The server prints its ready line or exits (its stdout then closes).
        BufReader::new(stdout).read_line(&mut server.ready)?;
        server.ready = server.ready.trim().to_string();
        if !server.ready.starts_with("ready:") {
            bail!("kfmap serve did not start: {:?}", server.ready);
        }
        Ok(server)
    }

    /// The server's process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

/// The map name the server benchmarks serve their map under.
pub const BENCH_MAP_NAME: &str = "bench";

/// Starts `kfmap serve` on `map` for the server benchmarks (ipc, soak): the map name
/// [`BENCH_MAP_NAME`] under `prefix`; `spin`: server polls instead of waiting on events.
pub fn start_bench_server(map: &Path, prefix: &str, spin: bool) -> anyhow::Result<ServerChild> {
    ServerChild::start(
        map,
        BENCH_MAP_NAME,
        prefix,
        if spin { &["--spin"] } else { &[] },
    )
}

impl Drop for ServerChild {
    fn drop(&mut self) {
        // SAFETY: kill(2) on our own child; SIGTERM lets it remove its resources.
        unsafe {
            libc::kill(self.child.id() as i32, libc::SIGTERM);
        }
        let _ = self.child.wait();
        if let Ok(config) = iceoryx_config(Some(&self.prefix)) {
            remove_prefix_files(&config, &self.prefix);
        }
    }
}

/// Runs `kfmap localize` against `server` on `dataset` with `args` (stderr shown) and
/// returns what it printed.
pub fn run_localize(
    server: &ServerChild,
    source: &Source,
    args: &[&OsStr],
) -> anyhow::Result<String> {
    let mut all = source_args(source);
    all.extend(["--rate".into(), "0".into()]);
    all.extend(args.iter().map(|a| a.to_os_string()));
    run_client(server, "localize", &all)
}

/// Runs `kfmap COMMAND --map-name .. --iceoryx-prefix .. ARGS` against `server`; its
/// stdout, or an error naming the command when it fails (its stderr passes through).
pub fn run_client(
    server: &ServerChild,
    command: &str,
    args: &[std::ffi::OsString],
) -> anyhow::Result<String> {
    let out = Command::new(std::env::current_exe()?)
        .args([
            command,
            "--map-name",
            &server.name,
            "--iceoryx-prefix",
            &server.prefix,
        ])
        .args(args)
        .stderr(Stdio::inherit())
        .output()
        .with_context(|| format!("run kfmap {command}"))?;
    if !out.status.success() {
        bail!("kfmap {command} failed ({})", out.status);
    }
    Ok(String::from_utf8(out.stdout)?)
}

/// The flags that name `source` to `kfmap localize` (`--dataset DIR`, or `--bag PATH
/// --points-topic T [--imu-topic T]`).
pub fn source_args(source: &Source) -> Vec<std::ffi::OsString> {
    match source {
        Source::Folder(dir) => vec!["--dataset".into(), dir.into()],
        Source::Bag(b) => {
            let mut args: Vec<std::ffi::OsString> = vec![
                "--bag".into(),
                (&b.path).into(),
                "--points-topic".into(),
                (&b.points_topic).into(),
            ];
            if let Some(imu) = &b.imu_topic {
                args.extend(["--imu-topic".into(), imu.into()]);
            }
            args
        }
    }
}
