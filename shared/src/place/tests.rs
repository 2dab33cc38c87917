use std::collections::HashSet;
use std::f64::consts::TAU;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::grid::SearchRegion;
use super::grid::{GridParams, GridView, PlaceGrid};
use super::search::{SearchParams, search, yaw_step};
use super::{GridBuilder, estimate_up};

/// True when a marked level-0 voxel lies within half a half-resolution voxel's
/// diagonal (0.43 times the resolution) of map point `p`: the grid holds map points by
/// the centres of their voxels of half its resolution. The reach is under half a
/// voxel, so its cube's corners and centre touch every voxel it does.
pub(crate) fn marked_near(view: &GridView<'_>, p: &[f64; 3]) -> bool {
    let g = view.grid_from_map() * Vector3::from(*p);
    let r = 0.44 * view.resolution();
    let reach = [-r, 0.0, r];
    reach.iter().any(|dx| {
        reach.iter().any(|dy| {
            reach
                .iter()
                .any(|dz| view.marked(0, view.voxel_of([g.x + dx, g.y + dy, g.z + dz])))
        })
    })
}

fn params(levels: usize) -> GridParams {
    GridParams {
        resolution: 1.0,
        levels,
        ..GridParams::default()
    }
}

fn region(min: [f64; 3], max: [f64; 3]) -> SearchRegion {
    SearchRegion { min, max }
}

/// A level-`l` voxel is marked exactly when a level-0 voxel of its cube is (brute
/// force over the marked set), inside the grid; from below the grid it bounds that.
#[test]
fn dilated_levels_mark_the_cubes_that_hold_a_marked_voxel() {
    let mut rng = StdRng::seed_from_u64(7);
    let marked: HashSet<[i64; 3]> = (0..60)
        .map(|_| {
            [
                rng.random_range(-5..15),
                rng.random_range(0..12),
                rng.random_range(-2..4),
            ]
        })
        .collect();
    let grid = PlaceGrid::from_voxels(
        &marked,
        &params(5),
        [0.0, 0.0, 0.0, 1.0],
        region([0.0; 3], [1.0; 3]),
    )
    .unwrap();
    let view = grid.view();
    let low = [-5, 0, -2]; // the grid's first voxel: the lowest marked key per axis
    for level in 0..5 {
        let side = 1_i64 << level;
        for _ in 0..3000 {
            let v = [
                rng.random_range(-20..25),
                rng.random_range(-20..20),
                rng.random_range(-20..10),
            ];
            let in_cube = marked.iter().any(|k| {
                (0..3).all(|a| {
                    let c = k[a] - low[a];
                    c >= v[a] && c < v[a] + side
                })
            });
            let answer = view.marked(level, v);
            if v.iter().all(|&c| c >= 0) {
                assert_eq!(answer, in_cube, "level {level}, voxel {v:?}");
            } else {
                assert!(
                    answer || !in_cube,
                    "level {level}, voxel {v:?}: not a bound"
                );
            }
        }
    }
}

/// The branch and bound finds the best placement an exhaustive scan of every yaw and
/// lattice translation finds (same lattice, same hit count).
#[test]
fn the_search_finds_the_exhaustive_optimum() {
    let mut rng = StdRng::seed_from_u64(11);
    for trial in 0..4 {
        let marked: HashSet<[i64; 3]> = (0..400)
            .map(|_| {
                [
                    rng.random_range(0..30),
                    rng.random_range(0..30),
                    rng.random_range(0..4),
                ]
            })
            .collect();
        let grid = PlaceGrid::from_voxels(
            &marked,
            &params(6),
            [0.0, 0.0, 0.0, 1.0],
            region([0.0; 3], [1.0; 3]),
        )
        .unwrap();
        let view = grid.view();
        let points: Vec<[f64; 3]> = (0..40)
            .map(|_| {
                [
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-1.0..1.0),
                ]
            })
            .collect();
        let area = region([5.3, 4.1, 0.2], [24.9, 22.7, 2.9]);
        let found = search(
            &view,
            &points,
            &area,
            &SearchParams {
                candidates: 1,
                min_hit_ratio: 0.0,
                ..SearchParams::default()
            },
            &UnitQuaternion::identity(),
        );
        let range = points.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
        let yaws = (TAU / yaw_step(1.0, range)).ceil() as usize;
        assert_eq!(found.yaws, yaws);
        let spans = [0, 1, 2].map(|a| ((area.max[a] - area.min[a]) / 1.0).floor() as i64 + 1);
        let mut best = 0;
        for y in 0..yaws {
            let rotation =
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), y as f64 * TAU / yaws as f64);
            for kx in 0..spans[0] {
                for ky in 0..spans[1] {
                    for kz in 0..spans[2] {
                        let t = Vector3::new(
                            area.min[0] + kx as f64,
                            area.min[1] + ky as f64,
                            area.min[2] + kz as f64,
                        );
                        let hits = points
                            .iter()
                            .filter(|p| {
                                let w = rotation * Vector3::from(**p) + t;
                                view.marked(0, view.voxel_of([w.x, w.y, w.z]))
                            })
                            .count();
                        best = best.max(hits);
                    }
                }
            }
        }
        let first = found.placements.first().expect("a placement");
        assert_eq!(first.hits as usize, best, "trial {trial}");
        // The placement's own pose scores what it says.
        let hits = points
            .iter()
            .filter(|p| {
                let w = first.pose * nalgebra::Point3::from(Vector3::from(**p));
                view.marked(0, view.voxel_of([w.x, w.y, w.z]))
            })
            .count();
        assert_eq!(hits, best, "trial {trial}");
    }
}

/// Points on a room's floor, ceiling and walls (8 x 6 x 3 m), sensor at 1.2 m height.
fn room(rng: &mut StdRng) -> Vec<Vector3<f64>> {
    let mut points = Vec::new();
    for _ in 0..20_000 {
        let (x, y) = (rng.random_range(-4.0..4.0), rng.random_range(-3.0..3.0));
        let z = rng.random_range(-1.2..1.8);
        let noise = rng.random_range(-0.01..0.01);
        points.push(match rng.random_range(0..6) {
            0 => Vector3::new(x, y, -1.2 + noise),
            1 => Vector3::new(x, y, 1.8 + noise),
            2 => Vector3::new(-4.0 + noise, y, z),
            3 => Vector3::new(4.0 + noise, y, z),
            4 => Vector3::new(x, -3.0 + noise, z),
            _ => Vector3::new(x, 3.0 + noise, z),
        });
    }
    points
}

/// A sensor tilted by a known rotation finds the room's up within 0.5 deg.
#[test]
fn up_is_found_from_the_floor_of_a_tilted_scan() {
    let mut rng = StdRng::seed_from_u64(3);
    let points = room(&mut rng);
    for (axis, deg) in [
        (Vector3::x_axis(), 0.0_f64),
        (Vector3::x_axis(), 12.0),
        (Vector3::y_axis(), -25.0),
    ] {
        // R_world_sensor: the scan holds R^-1 p.
        let tilt = UnitQuaternion::from_axis_angle(&axis, deg.to_radians());
        let scan: Vec<[f32; 3]> = points
            .iter()
            .map(|p| (tilt.inverse() * p).map(|v| v as f32).into())
            .collect();
        let up = estimate_up(&scan, 40.0).expect("floor planes");
        let truth = tilt.inverse() * Vector3::z();
        assert!(
            up.angle(&truth).to_degrees() < 0.5,
            "tilt {deg}: {:.2} deg",
            up.angle(&truth).to_degrees()
        );
    }
    // No plane at all (points filling whole voxels): no answer.
    let scattered: Vec<[f32; 3]> = (0..20_000)
        .map(|_| {
            [
                rng.random_range(-4.0..4.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(-2.0..2.0),
            ]
        })
        .collect();
    assert_eq!(estimate_up(&scattered, 40.0), None);
}

/// A grid built from a map tilted off its frame's z levels it back: the rotation is the
/// tilt's inverse within 0.5 deg, and every map point's voxel is marked.
#[test]
fn a_grid_levels_the_map_and_marks_every_point() {
    let mut rng = StdRng::seed_from_u64(5);
    let points = room(&mut rng);
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 4.0_f64.to_radians());
    let map_from_room = Isometry3::from_parts(Translation3::new(10.0, -3.0, 1.0), tilt);
    let params = GridParams {
        resolution: 0.5,
        ..GridParams::default()
    };
    let mut builder = GridBuilder::new(&params);
    builder.add_anchor(map_from_room.translation.vector.into());
    let in_map: Vec<[f64; 3]> = points
        .iter()
        .map(|p| (map_from_room * nalgebra::Point3::from(*p)).coords.into())
        .collect();
    builder.add_points(in_map.iter().copied());
    let grid = builder.finish(&params).unwrap();
    let view = grid.view();
    let levelled_up = view.grid_from_map() * (tilt * Vector3::z());
    assert!(levelled_up.angle(&Vector3::z()).to_degrees() < 0.5);
    for p in &in_map {
        assert!(marked_near(&view, p), "{p:?}");
    }
    // Far from the room nothing is marked.
    assert!(!view.marked(0, view.voxel_of([30.0, 30.0, 1.0])));
}

#[test]
fn bad_grid_options_are_named() {
    let bad = GridParams {
        resolution: 0.0,
        ..GridParams::default()
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("place-resolution")
    );
    let bad = GridParams {
        levels: 0,
        ..GridParams::default()
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("place-levels")
    );
    assert!(
        GridBuilder::new(&GridParams::default())
            .finish(&GridParams::default())
            .is_err()
    );
}
