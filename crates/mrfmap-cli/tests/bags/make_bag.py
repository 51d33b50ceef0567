"""Writes a ROS 2 bag (MCAP, or sqlite3 with --db3) of a TUM-layout dataset, without ROS: the
depth images on /camera/depth/image_rect_raw (32FC1 metres, the exact values mrfmap reads from
the PNGs), CameraInfo beside them, and the poses as TF: map -> base on /tf (at each image's
stamp) and base -> camera_depth_optical on /tf_static, or, with --direct, map ->
camera_depth_optical on /tf. Also a PoseStamped topic /camera/pose. Needs the `rosbags` package.

With --compressed png or --compressed rvl the images go on .../compressedDepth as
sensor_msgs/CompressedImage in compressedDepth format (16UC1 millimetres).

With --ros1 it writes a ROS 1 bag (OUT is the .bag file).

With --reverse the images are logged in reverse stamp order.

usage: make_bag.py DATASET OUT [--direct] [--db3] [--ros1] [--reverse] [--compressed png|rvl]
"""

import struct
import sys
import zlib
from pathlib import Path

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore


def read_png16(path):
    """A 16-bit grayscale, non-interlaced PNG as (width, height, rows of ints)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    pos, idat, width, height = 8, b"", 0, 0
    while pos < len(data):
        n = struct.unpack(">I", data[pos : pos + 4])[0]
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            assert depth == 16 and colour == 0 and interlace == 0, path
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw, stride, bpp = zlib.decompress(idat), width * 2, 2
    rows, prev = [], bytearray(stride)
    for y in range(height):
        f, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b, c = prev[i], (prev[i - bpp] if i >= bpp else 0)
            if f == 1:
                line[i] = (line[i] + a) & 255
            elif f == 2:
                line[i] = (line[i] + b) & 255
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append([line[2 * x] << 8 | line[2 * x + 1] for x in range(width)])
        prev = line
    return width, height, rows


def png16(width, height, values):
    """A 16-bit grayscale PNG of row-major values (filter 0 on every row)."""
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    raw = b"".join(b"\x00" + struct.pack(">%dH" % width, *values[y * width : (y + 1) * width]) for y in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def rvl(values):
    """Wilson's RVL: zero runs and zigzag deltas of non-zero runs in 3-bit groups with a
    continuation bit, nibbles packed most significant first into little-endian u32 words."""
    words, state = [], [0, 0]

    def put(n):
        state[0] = ((state[0] << 4) | n) & 0xFFFFFFFF
        state[1] += 1
        if state[1] == 8:
            words.append(state[0])
            state[0], state[1] = 0, 0

    def vle(v):
        while True:
            n = v & 7
            v >>= 3
            if v:
                n |= 8
            put(n)
            if not n & 8:
                break

    i, prev, n = 0, 0, len(values)
    while i < n:
        j = i
        while j < n and values[j] == 0:
            j += 1
        vle(j - i)
        k = j
        while k < n and values[k] != 0:
            k += 1
        vle(k - j)
        for v in values[j:k]:
            d = v - prev
            vle((d << 1) ^ (d >> 31) if d >= 0 else ((-d) << 1) - 1)
            prev = v
        i = k
    if state[1]:
        words.append((state[0] << (4 * (8 - state[1]))) & 0xFFFFFFFF)
    return struct.pack("<%dI" % len(words), *words)


def f32(x):
    return struct.unpack("<f", struct.pack("<f", x))[0]


def table(path):
    return [l.split() for l in path.read_text().splitlines() if l.strip() and not l.startswith("#")]


def main():
    root, out = Path(sys.argv[1]), Path(sys.argv[2])
    direct, db3 = "--direct" in sys.argv, "--db3" in sys.argv
    compressed = sys.argv[sys.argv.index("--compressed") + 1] if "--compressed" in sys.argv else None
    ros1 = "--ros1" in sys.argv
    cam = dict(l.split("=", 1) for l in (root / "camera.toml").read_text().splitlines() if "=" in l)
    cam = {k.strip(): float(v) for k, v in cam.items()}
    inv = f32(1.0 / cam["depth_scale"])
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    Image, Info, Header2 = (ts.types[n] for n in ["sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "std_msgs/msg/Header"])
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = (lambda **kw: Header2(seq=0, **kw)) if ros1 else Header2
    TF, TS, Tr, V3, Q = (ts.types[n] for n in ["tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped", "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion"])
    PS, Pose, Point, ROI = (ts.types[n] for n in ["geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/Pose", "geometry_msgs/msg/Point", "sensor_msgs/msg/RegionOfInterest"])
    import numpy as np

    poses = {float(r[0]): [float(v) for v in r[1:8]] for r in table(root / "groundtruth.txt")}
    plugin = StoragePlugin.SQLITE3 if db3 else StoragePlugin.MCAP
    with (Writer1(out) if ros1 else Writer(out, version=8, storage_plugin=plugin)) as w:
        if compressed:
            Compressed = ts.types["sensor_msgs/msg/CompressedImage"]
            c_img = w.add_connection("/camera/depth/image_rect_raw/compressedDepth", Compressed.__msgtype__, typestore=ts)
        else:
            c_img = w.add_connection("/camera/depth/image_rect_raw", Image.__msgtype__, typestore=ts)
        c_info = w.add_connection("/camera/depth/camera_info", Info.__msgtype__, typestore=ts)
        c_tf = w.add_connection("/tf", TF.__msgtype__, typestore=ts)
        c_static = w.add_connection("/tf_static", TF.__msgtype__, typestore=ts)
        c_pose = w.add_connection("/camera/pose", PS.__msgtype__, typestore=ts)
        Odom = ts.types["nav_msgs/msg/Odometry"]
        c_odom = w.add_connection("/camera/odom", Odom.__msgtype__, typestore=ts)
        c_ts = w.add_connection("/camera/transform", TS.__msgtype__, typestore=ts)
        stamp = lambda t: Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        tfs = lambda t, parent, child, p: TS(header=Header(stamp=stamp(t), frame_id=parent), child_frame_id=child, transform=Tr(translation=V3(x=p[0], y=p[1], z=p[2]), rotation=Q(x=p[3], y=p[4], z=p[5], w=p[6])))
        ser = lambda m: (ts.serialize_ros1 if ros1 else ts.serialize_cdr)(m, m.__msgtype__)
        optical = "camera_depth_optical"
        base_cam = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]  # identity: exact composition
        if not direct:
            w.write(c_static, 0, ser(TF(transforms=[tfs(0.0, "base", optical, base_cam)])))
        rows = [(float(r[0]), r[1]) for r in table(root / "depth.txt")]
        # --reverse logs the images last stamp first (as a bag recorded out of order).
        for t, path in reversed(rows) if "--reverse" in sys.argv else rows:
            p = min(poses.items(), key=lambda kv: abs(kv[0] - t))[1]
            ns = int(round(t * 1e9)) + 1
            width, height, rows = read_png16(root / path)
            depth = np.array([f32(v * inv) for row in rows for v in row], dtype="<f4")
            hdr = Header(stamp=stamp(t), frame_id=optical)
            k = np.array([cam["fx"], 0, cam["cx"], 0, cam["fy"], cam["cy"], 0, 0, 1], dtype=np.float64)
            mats = dict(D=np.zeros(5), K=k, R=np.eye(3).flatten(), P=np.zeros(12)) if ros1 else dict(d=np.zeros(5), k=k, r=np.eye(3).flatten(), p=np.zeros(12))
            info = Info(header=hdr, height=height, width=width, distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False), **mats)
            w.write(c_info, ns, ser(info))
            child = optical if direct else "base"
            w.write(c_tf, ns, ser(TF(transforms=[tfs(t, "map", child, p)])))
            if compressed:
                mm = [int(round(float(z) * 1000)) if z > 0 else 0 for z in depth]
                body = png16(width, height, mm) if compressed == "png" else struct.pack("<II", width, height) + rvl(mm)
                head = struct.pack("<iff", 0, 0.0, 0.0)
                fmt = "16UC1; compressedDepth " + compressed
                img = Compressed(header=hdr, format=fmt, data=np.frombuffer(head + body, dtype=np.uint8))
            else:
                img = Image(header=hdr, height=height, width=width, encoding="32FC1", is_bigendian=0, step=width * 4, data=depth.view(np.uint8))
            w.write(c_img, ns, ser(img))
            the_pose = Pose(position=Point(x=p[0], y=p[1], z=p[2]), orientation=Q(x=p[3], y=p[4], z=p[5], w=p[6]))
            w.write(c_pose, ns, ser(PS(header=Header(stamp=stamp(t), frame_id="map"), pose=the_pose)))
            PwC, TwC, Tw, V3z = (ts.types[n] for n in ["geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/TwistWithCovariance", "geometry_msgs/msg/Twist", "geometry_msgs/msg/Vector3"])
            zero = V3z(x=0.0, y=0.0, z=0.0)
            odom = Odom(header=Header(stamp=stamp(t), frame_id="map"), child_frame_id=optical, pose=PwC(pose=the_pose, covariance=np.zeros(36)), twist=TwC(twist=Tw(linear=zero, angular=zero), covariance=np.zeros(36)))
            w.write(c_odom, ns, ser(odom))
            w.write(c_ts, ns, ser(tfs(t, "map", optical, p)))


if __name__ == "__main__":
    main()
