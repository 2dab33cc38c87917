//! The `kfmap-ros2` binary's command line: what a user types before any DDS traffic.
//! (Its being an integration test of this crate is also what makes
//! `cargo test --workspace` build the binary the root's interop test runs.)

use std::path::PathBuf;
use std::process::{Command, Output};

use kfmap_geometry::options::ConfigFile;
use kfmap_ros2::config::Ros2Config;

fn node(args: &[&str], envs: &[(&str, &str)]) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_kfmap-ros2"));
    command.args(args).env_remove("ROS_DOMAIN_ID");
    for (key, value) in envs {
        command.env(key, value);
    }
    command.output().expect("run kfmap-ros2")
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("kfmap-ros2-cli-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn print_config_writes_the_built_in_defaults_as_a_loadable_file() {
    let out = node(&["--print-config"], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let dir = scratch("print");
    let path = dir.join("ros2.toml");
    std::fs::write(&path, &out.stdout).unwrap();
    let loaded = Ros2Config::load(Some(&path)).expect("the printed file loads");
    // The oracle: the defaults the library builds with no file at all.
    assert_eq!(loaded, Ros2Config::load(None).unwrap());
    let text = String::from_utf8(out.stdout).unwrap();
    for key in ["points", "initialpose", "domain-id", "[frames]"] {
        assert!(text.contains(key), "--print-config does not explain {key}");
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_bad_config_is_named_and_the_node_never_starts() {
    let dir = scratch("bad");
    let cases = [
        ("unknown.toml", "[topics]\npointz = \"/points\"\n", "pointz"),
        ("domain.toml", "[node]\ndomain-id = 300\n", "domain-id"),
        ("syntax.toml", "[node\n", "unknown.toml"),
    ];
    for (file, text, named) in cases {
        let path = dir.join(file);
        std::fs::write(&path, text).unwrap();
        let out = node(&["--config", path.to_str().unwrap()], &[]);
        let err = stderr(&out);
        assert!(!out.status.success(), "{file} was accepted: {err}");
        let named = if file == "syntax.toml" { file } else { named };
        assert!(
            err.contains(named),
            "{file}: the error does not name {named}: {err}"
        );
        assert!(
            !String::from_utf8_lossy(&out.stdout).contains("ready:"),
            "{file}"
        );
    }
    let missing = dir.join("absent.toml");
    let out = node(&["--config", missing.to_str().unwrap()], &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("absent.toml"), "{}", stderr(&out));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_domain_out_of_range_is_refused_from_the_flag_and_the_environment() {
    let out = node(&["--domain-id", "233"], &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("233"), "{}", stderr(&out));
    for text in ["seven", "400"] {
        let out = node(&[], &[("ROS_DOMAIN_ID", text)]);
        assert!(!out.status.success(), "ROS_DOMAIN_ID={text} accepted");
        assert!(stderr(&out).contains("ROS_DOMAIN_ID"), "{}", stderr(&out));
    }
}
