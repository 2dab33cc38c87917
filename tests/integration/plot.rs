//! `kfmap plot` end to end through the built binary: a simulated dataset baked into a
//! map, its pictures (PNG decoded and measured, SVG read as text), a trajectory against
//! its reference with a scan log, and bad inputs.

use crate::common;

use std::path::Path;
use std::process::Output;

use common::picture::Picture;
use common::{kfmap, run_ok, stderr, stdout, temp_dir};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;

/// Colour of lost/failed marks and of degraded marks (as `kfmap plot` draws them).
const LOST_RED: [u8; 3] = [228, 26, 28];
const DEGRADED_ORANGE: [u8; 3] = [255, 140, 0];

/// `kfmap plot --trajectory EST --ground-truth REF --out OUT EXTRA...`.
fn plot_trajectory(estimate: &Path, reference: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "plot",
        "--trajectory",
        estimate.to_str().unwrap(),
        "--ground-truth",
        reference.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    kfmap(&args)
}

/// `kfmap plot MAP --out OUT EXTRA...`, which must succeed; its printed line.
fn plot_map(map: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec![
        "plot",
        map.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    run_ok(&args)
}

/// Simulates 3 s of the courtyard and bakes it (poses from the dataset) with its
/// trajectory; `scans` bakes only that range.
fn baked(dir: &Path, name: &str, scans: Option<&str>) -> (std::path::PathBuf, std::path::PathBuf) {
    let sim = dir.join("sim");
    if !sim.exists() {
        common::simulate(&sim, "courtyard", "3", "16", &[]);
    }
    let map = dir.join(format!("{name}.kfmap"));
    let traj = dir.join(format!("{name}.tum"));
    let mut args = vec![
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
        "--trajectory-out",
        traj.to_str().unwrap(),
    ];
    if let Some(range) = scans {
        args.extend(["--scans", range]);
    }
    run_ok(&args);
    (map, traj)
}

#[test]
fn map_pictures_of_a_baked_simulation() {
    let tmp = temp_dir("plot-map");
    let (map, _) = baked(&tmp, "court", None);
    let png_path = tmp.join("court.png");
    let line = plot_map(&map, &png_path, &[]);
    assert!(line.contains("court.png:"), "{line}");
    assert!(
        line.contains("keyframes") && line.contains("drawn"),
        "{line}"
    );
    assert!(line.contains("1600x1200"), "{line}");
    let full = Picture::read(&png_path);
    full.assert_drawn(1600, 1200);

    // A map of the first scan alone is another picture.
    let (single, _) = baked(&tmp, "single", Some("0..1"));
    let single_png = tmp.join("single.png");
    let line = plot_map(&single, &single_png, &[]);
    assert!(line.contains(": 1 keyframe,"), "{line}");
    let one = Picture::read(&single_png);
    one.assert_drawn(1600, 1200);
    // One scan's points cover less of the chart (left of the colour bar) than 30 scans'.
    let chart = 1400;
    assert!(one.coloured_left_of(chart) < full.coloured_left_of(chart));

    // Another size, no edges: the requested dimensions.
    let small = tmp.join("small.png");
    plot_map(&map, &small, &["--no-edges", "--size", "900x700"]);
    Picture::read(&small).assert_drawn(900, 700);

    // SVG: text with drawing elements, points as rectangles, labels as text.
    let svg_path = tmp.join("court.svg");
    let line = plot_map(&map, &svg_path, &[]);
    assert!(line.contains("court.svg:"), "{line}");
    let svg = std::fs::read_to_string(&svg_path).unwrap();
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    assert!(svg.contains(r#"width="1600" height="1200""#));
    assert!(
        svg.matches("<rect").count() > 1000,
        "too few point elements"
    );
    assert!(
        svg.contains("<polygon") || svg.contains("<path"),
        "no keyframe arrows"
    );
    assert!(svg.contains("<text") && svg.contains("x (m)") && svg.contains("keyframes"));

    // Nothing else left beside the pictures (no temporary files).
    let leftovers: Vec<String> = std::fs::read_dir(&*tmp)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

/// A keyframe cloud: a 16 x 16 m grid of points 0.25 m apart, heights 0..3.9 m.
fn grid_cloud() -> PointCloud {
    let mut points = Vec::new();
    for i in 0..64 {
        for j in 0..64 {
            let z = ((i * 7 + j * 13) % 40) as f32 * 0.1;
            points.push([i as f32 * 0.25 - 8.0, j as f32 * 0.25 - 8.0, z]);
        }
    }
    PointCloud::from_points(points)
}

#[test]
fn more_points_colour_more_of_the_map() {
    let tmp = temp_dir("plot-oracle");
    let at = |x: f64, y: f64| Pose::translation(x, y, 0.0);
    let one = tmp.join("one.kfmap");
    let four = tmp.join("four.kfmap");
    common::bake_map(&one, &[(grid_cloud(), at(0.0, 0.0))], 0.05);
    let corners = [(-12.0, -12.0), (12.0, -12.0), (-12.0, 12.0), (12.0, 12.0)];
    let clouds: Vec<(PointCloud, Pose)> = corners
        .iter()
        .map(|&(x, y)| (grid_cloud(), at(x, y)))
        .collect();
    common::bake_map(&four, &clouds, 0.05);
    let picture = |map: &Path, name: &str| {
        let out = tmp.join(name);
        let line = plot_map(map, &out, &[]);
        (line, Picture::read(&out))
    };
    let (line, one) = picture(&one, "one.png");
    assert!(
        line.contains("1 keyframe, 4 096 points (drawn 4 096)"),
        "{line}"
    );
    one.assert_drawn(1600, 1200);
    let (line, four) = picture(&four, "four.png");
    assert!(
        line.contains("4 keyframes, 16 384 points (drawn 16 384)"),
        "{line}"
    );
    four.assert_drawn(1600, 1200);
    // Oracle: each point is a small square in a height colour (smaller when points are
    // denser), so four times the points colour far more of the chart (left of the
    // colour bar).
    let chart = |p: &Picture| p.coloured_left_of(1350);
    let (a, b) = (chart(&one), chart(&four));
    assert!(a > 10_000, "{a} coloured pixels for 4 096 points");
    assert!(
        2 * b > 3 * a,
        "{b} coloured pixels for 4 x the points of {a}"
    );
}

/// One `kfmap localize --json-lines` scan line.
fn scan_line(index: usize, t: f64, pose: &[f64], status: &str) -> String {
    serde_json::json!({
        "index": index,
        "t": t,
        "pose": pose,
        "status": status,
        "fitness": 0.9,
        "rmse_m": 0.05,
        "error_m": 0.01,
    })
    .to_string()
}

/// TUM lines (stamp, position) of a file.
fn tum(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(|w| w.parse().unwrap()).collect())
        .collect()
}

#[test]
fn trajectory_picture_with_a_scan_log() {
    let tmp = temp_dir("plot-trajectory");
    let (_, estimate) = baked(&tmp, "court", None);
    let reference = tmp.join("sim/poses_gt.txt");
    let poses = tum(&estimate);
    assert!(poses.len() >= 20);
    // Logs of the same scans: one with a lost and a degraded scan, one all ok, each
    // ending with the summary object (no index), which is skipped.
    let write_log = |name: &str, marked: bool| {
        let mut lines: Vec<String> = poses
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let status = match i {
                    7 if marked => "lost",
                    12 if marked => "degraded",
                    _ => "ok",
                };
                scan_line(i, p[0], &p[1..8], status)
            })
            .collect();
        lines.push(r#"{"scans": 30, "ok": 28, "degraded": 1, "lost": 1, "ate_m": 0.01}"#.into());
        let path = tmp.join(name);
        std::fs::write(&path, lines.join("\n") + "\n").unwrap();
        path
    };
    let marked_log = write_log("marked.jsonl", true);
    let ok_log = write_log("ok.jsonl", false);
    let plot_with = |log: &Path, out: &Path| {
        let log = log.to_str().unwrap();
        plot_trajectory(
            &estimate,
            &reference,
            out,
            &["--scan-log", log, "--size", "1200x1000"],
        )
    };
    let plot = |log: &Path, out: &Path| {
        let done = plot_with(log, out);
        assert!(done.status.success(), "{}", stderr(&done));
        stdout(&done)
    };
    let marked_png = tmp.join("marked.png");
    let line = plot(&marked_log, &marked_png);
    let n = poses.len();
    assert!(
        line.contains(&format!("{n} of {n} estimated poses matched")),
        "{line}"
    );
    assert!(line.contains("1 lost/failed, 1 degraded"), "{line}");
    let marked = Picture::read(&marked_png);
    marked.assert_drawn(1200, 1000);
    let ok_png = tmp.join("ok.png");
    let line = plot(&ok_log, &ok_png);
    assert!(line.contains("0 lost/failed, 0 degraded"), "{line}");
    let ok = Picture::read(&ok_png);
    ok.assert_drawn(1200, 1000);
    // Oracle: the lost scan adds red crosses and the degraded one orange triangles (in
    // both panels) to what the legend shows in both pictures.
    let (red, red_ok) = (marked.count(LOST_RED), ok.count(LOST_RED));
    assert!(
        red > red_ok + 40,
        "red pixels: {red} with a lost scan, {red_ok} without"
    );
    let (orange, orange_ok) = (marked.count(DEGRADED_ORANGE), ok.count(DEGRADED_ORANGE));
    assert!(
        orange > orange_ok + 40,
        "orange pixels: {orange} with a degraded scan, {orange_ok} without"
    );

    // SVG of the same.
    let svg_path = tmp.join("marked.svg");
    plot(&marked_log, &svg_path);
    let svg = std::fs::read_to_string(&svg_path).unwrap();
    assert!(svg.starts_with("<svg"));
    assert!(svg.contains("<circle") && svg.contains("<text"));
    assert!(svg.contains("position error (m)"));

    // A log of another run (its stamps 1000 s later) marks nothing: it is refused.
    let other = tmp.join("other.jsonl");
    let lines: Vec<String> = poses
        .iter()
        .enumerate()
        .map(|(i, p)| scan_line(i, p[0] + 1000.0, &p[1..8], "lost"))
        .collect();
    std::fs::write(&other, lines.join("\n")).unwrap();
    let refused = tmp.join("refused.png");
    let out = plot_with(&other, &refused);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("no logged scan is stamped within"));
    assert!(!refused.exists());
}

#[test]
fn trajectory_poses_are_matched_by_time_not_by_index() {
    let tmp = temp_dir("plot-matching");
    // A reference circle at 10 Hz, and an estimate of every third pose, 3 ms late and
    // 0.2 m off in x: matched by stamp, every error is 0.2 m (by index they would grow
    // to metres).
    let pose = |t: f64, dx: f64| {
        let a = t * 0.3;
        format!(
            "{t:.4} {:.6} {:.6} 0.5 0 0 0 1",
            10.0 * a.cos() + dx,
            10.0 * a.sin()
        )
    };
    let reference: Vec<String> = (0..200).map(|i| pose(i as f64 * 0.1, 0.0)).collect();
    let estimate: Vec<String> = (0..200)
        .step_by(3)
        .map(|i| pose(i as f64 * 0.1 + 0.003, 0.2))
        .collect();
    let (gt, est) = (tmp.join("gt.tum"), tmp.join("est.tum"));
    std::fs::write(&gt, reference.join("\n")).unwrap();
    std::fs::write(
        &est,
        format!("# t x y z qx qy qz qw\n{}\n", estimate.join("\n")),
    )
    .unwrap();
    let out_path = tmp.join("t.png");
    let plot = |extra: &[&str]| {
        let done = plot_trajectory(&est, &gt, &out_path, extra);
        assert!(done.status.success(), "{}", stderr(&done));
        stdout(&done)
    };
    let line = plot(&[]);
    // The shift of 3 ms moves the circle by 9 mm: errors stay 0.2 m within a few mm.
    assert!(line.contains("67 of 67 estimated poses matched"), "{line}");
    assert!(line.contains("RMSE 0.20"), "{line}");
    assert!(line.contains("max 0.20"), "{line}");
    Picture::read(&out_path).assert_drawn(1600, 1200);

    // --align moves the estimate onto the reference first: the 0.2 m offset goes, the
    // motion is printed, what is left is the 3 ms lag (under 1 cm on this circle).
    let line = plot(&["--align"]);
    assert!(line.contains("moved 0.20"), "{line}");
    assert!(line.contains("RMSE 0.00"), "{line}");

    // A tolerance below the 3 ms offset matches nothing: an error naming the clocks.
    let out = plot_trajectory(&est, &gt, &out_path, &["--max-dt-ms", "1"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("no estimated pose has a reference pose within 1 ms"));
}

#[test]
fn bad_inputs_exit_2_with_a_message() {
    let tmp = temp_dir("plot-errors");
    let gt = tmp.join("gt.tum");
    std::fs::write(&gt, "0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n").unwrap();
    let empty = tmp.join("empty.tum");
    std::fs::write(&empty, "# t x y z qx qy qz qw\n").unwrap();
    let not_a_map = tmp.join("notes.kfmap");
    std::fs::write(&not_a_map, "not a map at all").unwrap();
    let p = |name: &str| tmp.join(name).to_str().unwrap().to_string();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec!["plot".into(), p("notes.kfmap"), "--out".into(), p("x.jpg")],
            "unknown picture format '.jpg'",
        ),
        (
            vec![
                "plot".into(),
                p("missing.kfmap"),
                "--out".into(),
                p("x.png"),
            ],
            "missing.kfmap",
        ),
        (
            vec!["plot".into(), p("notes.kfmap"), "--out".into(), p("x.png")],
            "not a kfmap map file",
        ),
        (
            vec![
                "plot".into(),
                p("notes.kfmap"),
                "--trajectory".into(),
                p("gt.tum"),
                "--ground-truth".into(),
                p("gt.tum"),
                "--out".into(),
                p("x.png"),
            ],
            "cannot be used with",
        ),
        (
            vec!["plot".into(), "--out".into(), p("x.png")],
            "required arguments were not provided",
        ),
        (
            vec![
                "plot".into(),
                p("notes.kfmap"),
                "--out".into(),
                p("x.png"),
                "--size".into(),
                "1600".into(),
            ],
            "not a size",
        ),
        (
            vec![
                "plot".into(),
                p("notes.kfmap"),
                "--out".into(),
                p("x.png"),
                "--size".into(),
                "20x20".into(),
            ],
            "not a size",
        ),
        (
            vec![
                "plot".into(),
                "--trajectory".into(),
                p("empty.tum"),
                "--ground-truth".into(),
                p("gt.tum"),
                "--out".into(),
                p("x.png"),
            ],
            "is empty",
        ),
        (
            vec![
                "plot".into(),
                "--trajectory".into(),
                p("gt.tum"),
                "--ground-truth".into(),
                p("missing.tum"),
                "--out".into(),
                p("x.png"),
            ],
            "missing.tum",
        ),
        (
            vec![
                "plot".into(),
                "--trajectory".into(),
                p("gt.tum"),
                "--ground-truth".into(),
                p("gt.tum"),
                "--out".into(),
                p("x.pdf"),
            ],
            "unknown picture format '.pdf'",
        ),
    ];
    for (args, message) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = kfmap(&args);
        assert_eq!(
            out.status.code(),
            Some(2),
            "kfmap {args:?}: {}",
            stderr(&out)
        );
        assert!(
            stderr(&out).contains(message),
            "kfmap {args:?}: expected '{message}' in: {}",
            stderr(&out)
        );
    }
    // No picture, half or whole, was left by any failure.
    let names: Vec<String> = std::fs::read_dir(&*tmp)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names.iter().all(|n| !n.contains("x.")),
        "left behind: {names:?}"
    );
}
