"""Writes an MCAP bag of N synthetic 640x480 16UC1 depth images (a tilted plane) with CameraInfo
and /tf, for timing how fast mrfmap decodes bags (BENCHMARKS.md). Needs `rosbags` and numpy.

usage: make_perf_bag.py N OUT
"""

import sys

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore


def main():
    n, out = int(sys.argv[1]), sys.argv[2]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    v, u = np.mgrid[0:480, 0:640]
    depth = (1500 + 2 * u + v).astype("<u2")
    with Writer(out, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", typestore=ts)
        cc = w.add_connection("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        ct = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        for i in range(n):
            t = 1.0 + i / 30
            stamp = Time(sec=int(t), nanosec=int((t - int(t)) * 1e9))
            hdr = Header(stamp=stamp, frame_id="camera")
            k = np.array([525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1])
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            info = T["sensor_msgs/msg/CameraInfo"](header=hdr, height=480, width=640, distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).flatten(), p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)
            tr = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=0.01 * i, y=0.0, z=0.0), rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
            tf = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](header=Header(stamp=stamp, frame_id="map"), child_frame_id="camera", transform=tr)])
            img = T["sensor_msgs/msg/Image"](header=hdr, height=480, width=640, encoding="16UC1", is_bigendian=0, step=1280, data=depth.view(np.uint8).reshape(-1))
            ns = int(t * 1e9)
            w.write(cc, ns, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            w.write(ct, ns, ts.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
            w.write(ci, ns, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))


if __name__ == "__main__":
    main()
