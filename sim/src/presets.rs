//! Named sites: the scene, the path through it and how fast it is driven.

use rand::Rng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};

use super::noise::stream;
use super::scene::{SceneBuilder, Terrain};
use super::trajectory::{ClosedSpline, SpeedProfile, Trajectory};

/// A named site.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// 50 m courtyard: four building walls with doors, boxes, poles, trees and a thin
    /// fence in the middle; flat ground; loop at 2 m/s, about 90 m a lap.
    Courtyard,
    /// 300 m campus: buildings, tree trunks, poles and fences on gently rolling ground;
    /// 5 m/s loop of about 780 m around the central buildings.
    Campus,
    /// An 80 m tunnel 4 m wide (degenerate for registration), entered and left on a
    /// loop back outside over flat ground; 2 m/s, about 350 m a lap.
    Corridor,
    /// 1 km street grid: blocks of buildings, poles along the kerbs, trees, ground sloped
    /// 1 % along x; 10 m/s loop of about 1.2 km around two blocks.
    Street,
}

impl Preset {
    /// Every preset, in size order.
    pub const ALL: [Preset; 4] = [
        Preset::Courtyard,
        Preset::Campus,
        Preset::Corridor,
        Preset::Street,
    ];

    /// The name used on the command line and in `meta.toml`.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Courtyard => "courtyard",
            Preset::Campus => "campus",
            Preset::Corridor => "corridor",
            Preset::Street => "street",
        }
    }
}

impl std::str::FromStr for Preset {
    type Err = String;

    fn from_str(name: &str) -> Result<Self, String> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == name)
            .ok_or_else(|| {
                let names: Vec<&str> = Preset::ALL.iter().map(|p| p.name()).collect();
                format!(
                    "unknown preset '{name}'; choose one of: {}",
                    names.join(", ")
                )
            })
    }
}

/// A ready site: its scene and the vehicle's path.
pub struct Site {
    /// Everything a ray can hit.
    pub scene: super::scene::Scene,
    /// The ground-truth path.
    pub trajectory: Trajectory,
}

/// Minimum distance from the path centre line to any random obstacle, metres.
const CLEARANCE: f64 = 4.0;

/// Plan-view samples of the path, to keep obstacles off it.
fn path_samples(spline: &ClosedSpline) -> Vec<[f64; 2]> {
    let lap = spline.total_length();
    (0..400)
        .map(|k| {
            spline
                .eval(spline.param_at_distance(lap * k as f64 / 400.0))
                .0
                .into()
        })
        .collect()
}

fn clear_of(path: &[[f64; 2]], x: f64, y: f64, margin: f64) -> bool {
    path.iter()
        .all(|p| (p[0] - x).hypot(p[1] - y) > CLEARANCE + margin)
}

/// Random positions in `[x0, x1] x [y0, y1]` at least `margin` beyond the clearance.
fn scatter(
    rng: &mut StdRng,
    path: &[[f64; 2]],
    n: usize,
    area: [f64; 4],
    margin: f64,
) -> Vec<[f64; 2]> {
    let mut out = Vec::with_capacity(n);
    for _ in 0..n * 50 {
        if out.len() == n {
            break;
        }
        let (x, y) = (
            rng.random_range(area[0]..area[1]),
            rng.random_range(area[2]..area[3]),
        );
        if clear_of(path, x, y, margin) {
            out.push([x, y]);
        }
    }
    out
}

fn add_clutter(
    b: &mut SceneBuilder,
    rng: &mut StdRng,
    path: &[[f64; 2]],
    area: [f64; 4],
    counts: [usize; 3],
) {
    let [boxes, poles, trees] = counts;
    for [x, y] in scatter(rng, path, boxes, area, 2.5) {
        let size = [
            rng.random_range(1.5..5.0),
            rng.random_range(1.5..2.5),
            rng.random_range(1.2..2.8),
        ];
        b.add_box(x, y, size, rng.random_range(0.0..std::f64::consts::PI));
    }
    for [x, y] in scatter(rng, path, poles, area, 0.5) {
        b.add_cylinder(
            x,
            y,
            rng.random_range(0.06..0.15),
            rng.random_range(3.0..8.0),
        );
    }
    for [x, y] in scatter(rng, path, trees, area, 0.8) {
        b.add_cylinder(
            x,
            y,
            rng.random_range(0.15..0.45),
            rng.random_range(2.5..6.0),
        );
    }
}

/// Control points for a closed polygon whose corners the B-spline rounds within about
/// `radius` metres: each corner gets a point `radius` before and after it, and straight
/// runs between get points every 40 m (a B-spline is straight over collinear points).
fn rounded_corners(corners: &[[f64; 2]], radius: f64) -> Vec<[f64; 2]> {
    let n = corners.len();
    let mut out = Vec::new();
    for i in 0..n {
        let (c, next) = (corners[i], corners[(i + 1) % n]);
        let prev = corners[(i + n - 1) % n];
        let toward = |to: [f64; 2], d: f64| {
            let (dx, dy) = (to[0] - c[0], to[1] - c[1]);
            let len = dx.hypot(dy);
            [c[0] + dx / len * d, c[1] + dy / len * d]
        };
        out.extend([toward(prev, radius), c, toward(next, radius)]);
        let length = (next[0] - c[0]).hypot(next[1] - c[1]);
        let steps = ((length - 2.0 * radius) / 40.0).floor() as usize;
        for k in 1..steps {
            out.push(toward(
                next,
                radius + (length - 2.0 * radius) * k as f64 / steps as f64,
            ));
        }
    }
    out
}

/// Builds the site of `preset`; `seed` places the clutter.
pub fn build_site(preset: Preset, seed: u64) -> Site {
    let mut rng = stream(seed, u64::MAX - 1);
    let speed = |cruise: f64| SpeedProfile {
        cruise,
        ramp: 3.0,
        swing: 0.2,
        period: 12.0,
    };
    let (terrain, corners, radius, cruise): (Terrain, &[[f64; 2]], f64, f64) = match preset {
        Preset::Courtyard => (
            Terrain::Flat { z: 0.0 },
            &[[-12.0, -12.0], [12.0, -12.0], [12.0, 12.0], [-12.0, 12.0]],
            4.0,
            2.0,
        ),
        Preset::Campus => (
            Terrain::Rolling {
                amplitude: 1.5,
                wavelength: 160.0,
            },
            &[
                [-110.0, -90.0],
                [0.0, -100.0],
                [110.0, -90.0],
                [110.0, 90.0],
                [0.0, 100.0],
                [-110.0, 90.0],
            ],
            25.0,
            5.0,
        ),
        Preset::Corridor => (
            Terrain::Flat { z: 0.0 },
            &[[-70.0, 0.0], [70.0, 0.0], [70.0, 40.0], [-70.0, 40.0]],
            8.0,
            2.0,
        ),
        Preset::Street => (
            Terrain::Sloped { gx: 0.01, gy: 0.0 },
            &[
                [-200.0, -200.0],
                [200.0, -200.0],
                [200.0, 0.0],
                [-200.0, 0.0],
            ],
            12.0,
            10.0,
        ),
    };
    let control = rounded_corners(corners, radius);
    let spline = ClosedSpline::new(&control);
    let path = path_samples(&spline);
    let mut b = SceneBuilder::new(terrain);
    match preset {
        Preset::Courtyard => {
            b.add_ground(-40.0, -40.0, 40.0, 40.0, 2.0);
            let doors = [(10.0, 1.2, 2.2), (38.0, 3.0, 3.0)];
            b.add_wall([-25.0, -25.0], [25.0, -25.0], 8.0, 0.4, &doors);
            b.add_wall([25.0, -25.0], [25.0, 25.0], 10.0, 0.4, &doors[..1]);
            b.add_wall([25.0, 25.0], [-25.0, 25.0], 7.0, 0.4, &doors);
            b.add_wall([-25.0, 25.0], [-25.0, -25.0], 9.0, 0.4, &[(25.0, 1.0, 2.1)]);
            b.add_thin_wall([-4.0, 1.0], [4.0, -1.0], 2.2);
            add_clutter(
                &mut b,
                &mut rng,
                &path,
                [-23.0, 23.0, -23.0, 23.0],
                [8, 10, 8],
            );
        }
        Preset::Campus => {
            b.add_ground(-180.0, -160.0, 180.0, 160.0, 4.0);
            for [x, y] in scatter(&mut rng, &path, 14, [-170.0, 170.0, -150.0, 150.0], 22.0) {
                let size = [
                    rng.random_range(12.0..30.0),
                    rng.random_range(10.0..25.0),
                    rng.random_range(6.0..20.0),
                ];
                b.add_box(x, y, size, rng.random_range(0.0..std::f64::consts::PI));
            }
            for _ in 0..6 {
                let [[x, y]] = scatter(&mut rng, &path, 1, [-150.0, 150.0, -140.0, 140.0], 8.0)[..]
                else {
                    continue;
                };
                let a: f64 = rng.random_range(0.0..std::f64::consts::PI);
                b.add_thin_wall(
                    [x - 6.0 * a.cos(), y - 6.0 * a.sin()],
                    [x + 6.0 * a.cos(), y + 6.0 * a.sin()],
                    1.5,
                );
            }
            add_clutter(
                &mut b,
                &mut rng,
                &path,
                [-170.0, 170.0, -150.0, 150.0],
                [30, 60, 120],
            );
        }
        Preset::Corridor => {
            b.add_ground(-100.0, -40.0, 100.0, 80.0, 4.0);
            b.add_tunnel([-40.0, 0.0], [40.0, 0.0], 4.0, 3.0);
            b.add_wall([-90.0, 60.0], [90.0, 60.0], 6.0, 0.5, &[]);
            add_clutter(
                &mut b,
                &mut rng,
                &path,
                [-95.0, 95.0, 10.0, 58.0],
                [20, 20, 20],
            );
            add_clutter(
                &mut b,
                &mut rng,
                &path,
                [-95.0, 95.0, -35.0, -5.0],
                [10, 10, 10],
            );
        }
        Preset::Street => {
            b.add_ground(-520.0, -520.0, 520.0, 520.0, 4.0);
            // Streets every 200 m; each block holds a ring of buildings set back 12 m.
            for bx in -2..2 {
                for by in -2..2 {
                    let (x0, y0) = (bx as f64 * 200.0 + 12.0, by as f64 * 200.0 + 12.0);
                    let mut x = x0;
                    while x < x0 + 170.0 {
                        let width = rng.random_range(15.0..35.0);
                        let height = rng.random_range(8.0..30.0);
                        b.add_box(x + width / 2.0, y0 + 10.0, [width - 2.0, 20.0, height], 0.0);
                        b.add_box(
                            x + width / 2.0,
                            y0 + 166.0,
                            [width - 2.0, 20.0, height],
                            0.0,
                        );
                        x += width;
                    }
                }
            }
            for k in -20..=20 {
                for line in [-200.0, 0.0, 200.0] {
                    let along = k as f64 * 25.0;
                    for [x, y] in [[along, line + 7.0], [line + 7.0, along]] {
                        if clear_of(&path, x, y, 0.5) {
                            b.add_cylinder(x, y, 0.12, 6.0);
                        }
                    }
                }
            }
            add_clutter(
                &mut b,
                &mut rng,
                &path,
                [-500.0, 500.0, -500.0, 500.0],
                [40, 0, 150],
            );
        }
    }
    Site {
        scene: b.build(),
        trajectory: Trajectory::new(spline, terrain, speed(cruise), 1.8),
    }
}
