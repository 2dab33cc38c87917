use nalgebra::{Point3, UnitQuaternion, Vector3};

use super::*;
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_testdata::Scratch;

fn ray(origin: Vector3<f64>, dir: Vector3<f64>) -> Ray {
    Ray {
        origin,
        dir: dir.normalize(),
    }
}

#[test]
fn plane_at_known_distance_gives_exact_ranges() {
    let mut b = SceneBuilder::new(Terrain::Flat { z: 0.0 });
    let big = 1000.0;
    b.add_quad(
        Vector3::new(10.0, -big, -big),
        Vector3::new(10.0, big, -big),
        Vector3::new(10.0, big, big),
        Vector3::new(10.0, -big, big),
    );
    let scene = b.build();
    for az in [-1.2f64, -0.5, 0.0, 0.3, 1.1] {
        for el in [-0.4f64, 0.0, 0.25] {
            let dir = Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let range = scene.cast(&ray(Vector3::zeros(), dir), 1e4).unwrap();
            assert!(
                (range - 10.0 / (el.cos() * az.cos())).abs() < 1e-9,
                "az {az} el {el}: {range}"
            );
        }
    }
}

#[test]
fn deskewed_sweep_over_flat_ground_lands_exactly_on_the_ground() {
    // Ground only, noise off, moving and turning: every deskewed point mapped through the
    // true pose at the sweep start lies on z = 0, to the f32 storage resolution.
    let mut b = SceneBuilder::new(Terrain::Flat { z: 0.0 });
    b.add_ground(-200.0, -200.0, 200.0, 200.0, 4.0);
    let scene = b.build();
    let spline = ClosedSpline::new(&[[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]);
    let speed = SpeedProfile {
        cruise: 8.0,
        ramp: 1.0,
        swing: 0.2,
        period: 5.0,
    };
    let trajectory = Trajectory::new(spline, Terrain::Flat { z: 0.0 }, speed, 1.8);
    let params = LidarParams {
        range_noise_sigma: 0.0,
        dropout: 0.0,
        ..LidarParams::default()
    };
    let cloud = sweep(
        &scene,
        &trajectory,
        &params,
        3.0,
        &mut rand::SeedableRng::seed_from_u64(1),
    );
    assert!(cloud.len() > 20_000, "{}", cloud.len());
    let start = trajectory.pose(3.0);
    for p in &cloud.points {
        let map = start * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        assert!(map.z.abs() < 2e-5, "{}", map.z);
    }
}

#[test]
fn cylinder_hits_satisfy_its_equation() {
    let (cx, cy, r, z1) = (4.0, -2.0, 0.35, 3.0);
    let mut b = SceneBuilder::new(Terrain::Flat { z: 0.0 });
    b.add_cylinder(cx, cy, r, z1);
    let scene = b.build();
    let (mut side, mut cap) = (0, 0);
    for i in 0..2000 {
        let a = -0.6 + 1.2 * i as f64 / 2000.0;
        for (height, el) in [
            (1.5, -0.3f64),
            (1.5, 0.1),
            (1.5, 0.5),
            (6.0, -0.6),
            (6.0, -0.9),
        ] {
            let origin = Vector3::new(0.0, 0.0, height);
            let dir = Vector3::new(
                (a - 0.46).cos() * el.cos(),
                (a - 0.46).sin() * el.cos(),
                el.sin(),
            );
            if let Some(t) = scene.cast(&ray(origin, dir), 100.0) {
                let p = origin + dir.normalize() * t;
                let radial = ((p.x - cx).powi(2) + (p.y - cy).powi(2)).sqrt();
                if (p.z - z1).abs() < 1e-9 {
                    cap += 1;
                    assert!(radial <= r + 1e-9);
                } else {
                    side += 1;
                    assert!((radial - r).abs() < 1e-9, "{radial}");
                    assert!(p.z >= -0.5 && p.z <= z1);
                }
            }
        }
    }
    assert!(side > 100 && cap > 10, "{side} side, {cap} cap hits");
}

#[test]
fn integrating_the_noiseless_imu_reproduces_the_pose_change() {
    for preset in [Preset::Courtyard, Preset::Campus] {
        let config = SimConfig {
            preset,
            seconds: 8.0,
            tilt_deg: [2.0, -3.0],
            ..SimConfig::default()
        }
        .without_noise();
        let sim = Simulation::new(config.clone()).unwrap();
        let traj = &sim.site().trajectory;
        let (t0, t1) = (5.0, 6.0);
        let samples = imu_samples(
            traj,
            &config.imu,
            &config.gravity_map(),
            t0,
            t1,
            config.seed,
        );
        let g = config.gravity_map();
        let start = traj.pose(t0);
        let mut rotation: UnitQuaternion<f64> = start.rotation;
        let mut position = start.translation.vector;
        let mut velocity = traj.velocity(t0);
        for pair in samples.windows(2) {
            let dt = pair[1].t - pair[0].t;
            let w = (Vector3::from(pair[0].gyro) + Vector3::from(pair[1].gyro)) / 2.0;
            let next_rotation = rotation * UnitQuaternion::from_scaled_axis(w * dt);
            let a0 = rotation * Vector3::from(pair[0].acc) + g;
            let a1 = next_rotation * Vector3::from(pair[1].acc) + g;
            position += velocity * dt + (a0 * 2.0 + a1) * (dt * dt / 6.0);
            velocity += (a0 + a1) * (dt / 2.0);
            rotation = next_rotation;
        }
        let end = traj.pose(t1);
        let position_error = (position - end.translation.vector).norm();
        let rotation_error = rotation.angle_to(&end.rotation);
        println!(
            "{preset:?}: IMU dead reckoning over 1 s: {position_error:.2e} m, {rotation_error:.2e} rad"
        );
        assert!(position_error < 1e-3, "{preset:?}: {position_error} m");
        assert!(rotation_error < 1e-4, "{preset:?}: {rotation_error} rad");
        // The run moved and turned enough for this to mean something.
        assert!((end.translation.vector - start.translation.vector).norm() > 1.0);
    }
}

#[test]
fn static_accelerometer_reads_the_tilted_gravity() {
    // At t = 0 the vehicle is at rest: the accelerometer reads -g in the body frame.
    let config = SimConfig {
        tilt_deg: [3.0, -2.0],
        ..SimConfig::default()
    }
    .without_noise();
    let sim = Simulation::new(config.clone()).unwrap();
    let first = sim.imu()[0];
    let pose = sim.site().trajectory.pose(0.0);
    let up_map = pose.rotation * Vector3::from(first.acc);
    assert!((up_map + config.gravity_map()).norm() < 1e-3, "{up_map}");
    assert!((config.gravity_map().norm() - GRAVITY).abs() < 1e-12);
}

fn all_files(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in ["", "scans"] {
        let mut names: Vec<_> = std::fs::read_dir(dir.join(sub))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect();
        names.sort();
        out.extend(names.into_iter().map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        }));
    }
    out
}

#[test]
fn same_seed_gives_byte_identical_datasets() {
    let config = SimConfig {
        seconds: 0.5,
        lidar: LidarParams {
            beams: 16,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    };
    let scratch = Scratch::new("sim-deterministic");
    let (a, b, c) = (scratch.file("a"), scratch.file("b"), scratch.file("c"));
    let quiet = |_: usize, _: usize| {};
    write_dataset(config.clone(), &a, false, &quiet).unwrap();
    // Built on one thread the second time: the bytes must not depend on scheduling.
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    one.install(|| write_dataset(config.clone(), &b, false, &quiet))
        .unwrap();
    let files_a = all_files(&a);
    assert_eq!(files_a.len(), 4 + 5); // imu.csv, meta.toml, poses_gt.txt, poses_imu_gt.txt + 5 scans
    assert_eq!(files_a, all_files(&b));
    write_dataset(
        SimConfig {
            seed: 2,
            ..config.clone()
        },
        &c,
        false,
        &quiet,
    )
    .unwrap();
    let scan_a = std::fs::read(a.join("scans/000000.pcd")).unwrap();
    assert_ne!(scan_a, std::fs::read(c.join("scans/000000.pcd")).unwrap());
    // A non-empty folder is refused without force.
    assert!(matches!(
        write_dataset(SimConfig::default(), &a, false, &quiet),
        Err(SimError::NotEmpty(_))
    ));
}

#[test]
fn raw_scans_read_back_with_view_directions_toward_the_sensor() {
    let mut config = SimConfig {
        seconds: 0.2,
        ..SimConfig::default()
    }
    .without_noise();
    config.lidar.deskew = false;
    let scratch = Scratch::new("sim-raw");
    let dir = scratch.file("raw");
    write_dataset(config, &dir, false, &|_, _| {}).unwrap();
    let loaded = read_cloud(&dir.join("scans/000001.pcd"), &ReadOptions::default()).unwrap();
    let cloud = loaded.cloud;
    assert_eq!(loaded.filter.unwrap().dropped(), 0);
    let (views, times) = (
        cloud.view_dirs.as_ref().unwrap(),
        cloud.time.as_ref().unwrap(),
    );
    for ((p, v), t) in cloud.points.iter().zip(views).zip(times) {
        let p = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        assert!(
            (Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64) + p.normalize()).norm() < 1e-5
        );
        assert!((0.0..0.1).contains(t));
    }
    let gt = kfmap_geometry::io::read_trajectory(&dir.join("poses_gt.txt")).unwrap();
    assert_eq!(gt.poses.len(), 2);
    let imu = kfmap_geometry::imu::read_imu_csv(&dir.join("imu.csv")).unwrap();
    assert_eq!(imu.len(), 41); // 0.2 s at 200 Hz, both ends included
}

#[test]
fn every_preset_builds_a_clear_path_and_real_scans() {
    for preset in Preset::ALL {
        let sim = Simulation::new(
            SimConfig {
                preset,
                seconds: 30.0,
                ..SimConfig::default()
            }
            .without_noise(),
        )
        .unwrap();
        for index in [0, 150, 299] {
            let scan = sim.scan(index);
            assert!(
                scan.cloud.len() > 20_000,
                "{preset:?} scan {index}: {} points",
                scan.cloud.len()
            );
            // Nothing within 1.5 m of the sensor: the path does not run through obstacles.
            let nearest = scan
                .cloud
                .points
                .iter()
                .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
                .fold(f32::INFINITY, f32::min);
            assert!(
                nearest > 1.5,
                "{preset:?} scan {index}: a return at {nearest} m"
            );
        }
        assert_eq!(preset.name().parse::<Preset>().unwrap(), preset);
    }
    assert!("plaza".parse::<Preset>().unwrap_err().contains("courtyard"));
}

#[test]
fn invalid_parameters_are_named() {
    let bad = SimConfig {
        lidar: LidarParams {
            beams: 40,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    };
    assert_eq!(bad.validate().unwrap_err().option, "beams");
    let bad = SimConfig {
        seconds: -1.0,
        ..SimConfig::default()
    };
    assert_eq!(bad.validate().unwrap_err().option, "seconds");
}

/// `cruise_speed` overrides the preset's: at the end of the start from rest (3 s) the
/// speed is the cruise speed exactly (the swing starts there at zero), on the same path.
#[test]
fn cruise_speed_override_drives_the_same_path_faster() {
    let speed_at_cruise = |cruise_speed: Option<f64>| {
        let sim = Simulation::new(SimConfig {
            cruise_speed,
            ..SimConfig::default()
        })
        .unwrap();
        let path = &sim.site().trajectory;
        (path.velocity(3.0).norm(), path.spline().total_length())
    };
    let (preset, lap) = speed_at_cruise(None);
    assert!((preset - 2.0).abs() < 1e-4, "{preset}");
    for cruise in [1.0, 4.0] {
        let (speed, same_lap) = speed_at_cruise(Some(cruise));
        assert!((speed - cruise).abs() < 1e-4, "{cruise}: {speed}");
        assert_eq!(same_lap, lap);
    }
    let bad = SimConfig {
        cruise_speed: Some(0.0),
        ..SimConfig::default()
    };
    assert_eq!(bad.validate().unwrap_err().option, "speed");
}
