//! `--vertical-angle-offset-deg`: how a command that sends scans reads them, the same
//! correction bake.toml's `[input]` applied to the map's scans; shared by `localize`
//! and `relocalize`.

use kfmap_bake::config::BakeConfig;

/// The sensor's correction applied to every scan read.
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct SensorArgs {
    /// The sensor's vertical-angle offset, degrees (-5 to 5): every return's elevation
    /// raised by it on load, as bake.toml's [input] vertical-angle-offset-deg did for the
    /// map (KITTI's HDL-64E: 0.205).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub vertical_angle_offset_deg: f64,
}

impl SensorArgs {
    /// The bake's defaults with this correction, checked as bake.toml's `[input]` is.
    pub fn scan_config(&self) -> anyhow::Result<BakeConfig> {
        let mut config = BakeConfig::default();
        config.input.vertical_angle_offset_deg = self.vertical_angle_offset_deg;
        config
            .input
            .validate()
            .map_err(|e| anyhow::anyhow!("--{}: {e}", e.option))?;
        Ok(config)
    }
}
