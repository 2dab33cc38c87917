//! How a command that sends scans reads them, as the map's bake read its scans:
//! `--bake-config` (the bake.toml the map was baked with: its `[input]` and its
//! `[build.odometry]` deskew and sweep) and `--vertical-angle-offset-deg`; shared by
//! `localize` and `relocalize`.

use std::path::PathBuf;

use kfmap_bake::config::BakeConfig;
use kfmap_geometry::options::ConfigFile;

/// The sensor's corrections applied to every scan read.
#[derive(clap::Args, Debug, Clone)]
pub struct SensorArgs {
    /// The bake.toml the map was baked with: its [input] (vertical-angle-offset-deg,
    /// bin-layout) applies to every scan read, and its [build.odometry] deskew and sweep
    /// to `localize`'s deskewing (default: bake.toml's defaults).
    #[arg(long, value_name = "BAKE_TOML")]
    pub bake_config: Option<PathBuf>,
    /// The sensor's vertical-angle offset, degrees (-5 to 5): every return's elevation
    /// raised by it on load, as bake.toml's [input] vertical-angle-offset-deg did for the
    /// map (KITTI's HDL-64E: 0.205; default: --bake-config's, else 0).
    #[arg(long, allow_negative_numbers = true)]
    pub vertical_angle_offset_deg: Option<f64>,
}

impl SensorArgs {
    /// `--bake-config` (or the defaults) with the flags' overrides, checked as bake.toml's
    /// `[input]` is.
    pub fn scan_config(&self) -> anyhow::Result<BakeConfig> {
        let mut config = BakeConfig::load(self.bake_config.as_deref())?;
        if let Some(offset) = self.vertical_angle_offset_deg {
            config.input.vertical_angle_offset_deg = offset;
        }
        config
            .input
            .validate()
            .map_err(|e| anyhow::anyhow!("--{}: {e}", e.option))?;
        Ok(config)
    }
}
