#!/usr/bin/env python3
"""Does a dataset's reference fit its scans? For each consecutive pair of KITTI-style scans
(../shared/data/kitti00 by default: velodyne .bin, poses_velo_kitti.txt), scan k+1 is placed
on scan k twice: by the reference's relative pose, and by small_gicp's GICP started from
it (an implementation independent of kfmap). For each placement: the step length, and
how well the structure above the road coincides (points of scan k+1 more than 1.2 m
above the sensor's floor, 3-40 m away: their nearest neighbour in scan k, median
distance and share within 10 cm).

If the reference were the truth, the registration would land near it and both
placements would align about as well. On kitti00 the registration aligns 86-90 % of
that structure within 10 cm and the reference 56-72 %, 0.12-0.17 m shorter per step:
the six scans do not fit the six reference poses, so an aligned ATE against them
ranks methods by how much forward motion they leave out, not by accuracy.

Install `small-gicp numpy` in a venv outside the repository (see small_gicp_reg.py).
`python kitti_reference_check.py [--dataset D]`
"""
import argparse
import pathlib

import numpy as np
import small_gicp

DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "kitti00"
# The HDL-64E sits about 1.73 m above the road on the KITTI car.
ABOVE_SENSOR_M = -0.5


def read_scan(path):
    points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    reach = np.linalg.norm(points[:, :2], axis=1)
    return points[(reach > 3.0) & (reach < 40.0)]


def read_reference(dataset):
    rows = np.loadtxt(dataset / "poses_velo_kitti.txt", ndmin=2)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def coincidence(source, target, T_target_source):
    """Median nearest-neighbour distance (m) and share within 0.1 m of the structure of
    `source` placed by `T_target_source` on `target`'s structure."""
    placed = source @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    placed = placed[placed[:, 2] > ABOVE_SENSOR_M]
    tree = small_gicp.KdTree(target[target[:, 2] > ABOVE_SENSOR_M])
    _, squared = tree.batch_nearest_neighbor_search(placed)
    distance = np.sqrt(np.asarray(squared))
    return np.median(distance), np.mean(distance < 0.1)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=pathlib.Path, default=DATA)
    args = parser.parse_args()
    reference = read_reference(args.dataset)
    paths = sorted(args.dataset.glob("*.bin"))
    print("pair   placement  step (m)  median NN (cm)  within 10 cm")
    for k in range(len(paths) - 1):
        target, source = read_scan(paths[k]), read_scan(paths[k + 1])
        relative = np.linalg.inv(reference[k]) @ reference[k + 1]
        registered = small_gicp.align(
            target, source, init_T_target_source=relative, registration_type="GICP",
            downsampling_resolution=0.25, max_correspondence_distance=1.0, num_threads=2,
        ).T_target_source
        for name, T in (("reference", relative), ("GICP", registered)):
            median, share = coincidence(source, target, T)
            print(f"{k}-{k + 1}    {name:<9}  {np.linalg.norm(T[:3, 3]):8.3f}  {median * 100:14.1f}  {share * 100:10.1f} %")


if __name__ == "__main__":
    main()
