//! Fuzzes the config loader: any text, as `server.toml` or `bake.toml`, gives a
//! config or a named `ConfigError` (parse, unknown key, value out of range), never a
//! panic. A config that validates writes back (`toml::to_string`) and loads again to
//! the same TOML, and a bake config's map options survive the archive's TOML round
//! trip (`options_toml` in the writer, `toml::from_str` in `open_map`).
//! Run: `cargo +nightly fuzz run config`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_bake::config::BakeConfig;
use kfmap_geometry::options::{ConfigError, ConfigFile};
use kfmap_map::map::KeyframeMapOptions;
use kfmap_service::config::ServerConfig;
use libfuzzer_sys::fuzz_target;

fn round_trip<C: ConfigFile + serde::Serialize>(config: &C, path: &Path) {
    let text = toml::to_string(config)
        .unwrap_or_else(|e| panic!("a valid config does not serialize: {e}"));
    let again = C::from_toml(&text, path)
        .unwrap_or_else(|e| panic!("a valid config, written back, does not load: {e}\n{text}"));
    let text_again = toml::to_string(&again).expect("serializes");
    assert_eq!(
        text, text_again,
        "a valid config changes in a write/load round trip"
    );
}

fn named(e: &ConfigError) {
    let message = e.to_string();
    assert!(!message.is_empty());
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let strict = common::strict();
    let path = Path::new("server.toml");
    match ServerConfig::from_toml(text, path) {
        Ok(config) => {
            if strict {
                round_trip(&config, path);
            }
        }
        Err(e) => named(&e),
    }
    let path = Path::new("bake.toml");
    match BakeConfig::from_toml(text, path) {
        Ok(config) => {
            let _ = config.keyframes.decider();
            let options = config.map_options();
            if strict {
                round_trip(&config, path);
                assert!(options.validate().is_ok());
                let stored = toml::to_string(&options).unwrap_or_else(|e| {
                    panic!("map options of a valid bake.toml do not serialize: {e}")
                });
                let read: KeyframeMapOptions = toml::from_str(&stored).unwrap_or_else(|e| {
                    panic!("map options as stored do not parse: {e}\n{stored}")
                });
                assert_eq!(toml::to_string(&read).expect("serializes"), stored);
            }
        }
        Err(e) => named(&e),
    }
});
