"""Writes an MCAP bag of a planar laser in a 4 m x 4 m square room (walls at x, y = +-2 m),
seen from four poses: sensor_msgs/LaserScan on /scan (180 beams over 180 degrees, frame
`laser`, one beam per scan with no return), the same returns as a sensor_msgs/PointCloud2 on
/points, the laser's pose as /tf map -> laser at z = 0.025 m.
The same room as the CLI test's CARMEN log. Needs `rosbags` and numpy.

usage: make_scan_bag.py OUT
"""

import math
import sys

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore


def main():
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    with Writer(sys.argv[1], version=8, storage_plugin=StoragePlugin.MCAP) as w:
        cs = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        cp = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        ct = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        for i, (x, y, th) in enumerate([(0.0, 0.0, 0.0), (0.5, 0.3, 1.0), (-0.6, -0.4, 2.0), (0.2, -0.5, 4.0)]):
            t = 1.0 + i
            stamp = Time(sec=int(t), nanosec=0)
            ranges = []
            for k in range(180):
                a = th - math.pi / 2 + k * math.pi / 180
                dx, dy = math.cos(a), math.sin(a)
                cand = [v for v in ((2 - x) / dx if dx else -1, (-2 - x) / dx if dx else -1, (2 - y) / dy if dy else -1, (-2 - y) / dy if dy else -1) if v > 0]
                ranges.append(30.0 if k == 90 else min(cand))
            scan = T["sensor_msgs/msg/LaserScan"](header=Header(stamp=stamp, frame_id="laser"), angle_min=-math.pi / 2, angle_max=math.pi / 2, angle_increment=math.pi / 180, time_increment=0.0, scan_time=0.1, range_min=0.05, range_max=30.0, ranges=np.array(ranges, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32))
            q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))
            tr = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.025), rotation=q)
            tf = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](header=Header(stamp=stamp, frame_id="map"), child_frame_id="laser", transform=tr)])
            w.write(ct, int(t * 1e9), ts.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
            w.write(cs, int(t * 1e9), ts.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
            # The returns as a cloud in the laser's frame: x y z float32 behind 4 padding bytes.
            hits = [(r * math.cos(-math.pi / 2 + k * math.pi / 180), r * math.sin(-math.pi / 2 + k * math.pi / 180)) for k, r in enumerate(ranges) if k != 90]
            raw = np.zeros((len(hits), 4), dtype="<f4")
            raw[:, 1:3] = np.array(hits, dtype="<f4")
            F = T["sensor_msgs/msg/PointField"]
            fields = [F(name=n, offset=o, datatype=7, count=1) for n, o in (("x", 4), ("y", 8), ("z", 12))]
            cloud = T["sensor_msgs/msg/PointCloud2"](header=Header(stamp=stamp, frame_id="laser"), height=1, width=len(hits), fields=fields, is_bigendian=False, point_step=16, row_step=16 * len(hits), data=raw.view(np.uint8).reshape(-1), is_dense=True)
            w.write(cp, int(t * 1e9), ts.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2"))


if __name__ == "__main__":
    main()
