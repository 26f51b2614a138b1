from __future__ import annotations

import typing

import numpy as np
import pytest

from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics, RgbdFrame, pose_to_matrix
from octolog.schemas import codec, logview, msgtypes, posemsgs, rgbdmsgs, topics


def _frame(seq: int = 3) -> RgbdFrame:
    rng = np.random.default_rng(seq)
    intr = Intrinsics(32, 24, 30.0, 31.0, 15.5, 11.5, (0.1, -0.2, 0.0, 0.0, 0.05))
    return RgbdFrame(seq, 1_700_000_000_123_456_789, rng.integers(0, 255, (24, 32, 3), dtype=np.uint8),
                     rng.integers(0, 65535, (24, 32), dtype=np.uint16), 0.0002, intr)


def test_rgbd_round_trip_is_exact():
    f = _frame()
    data = codec.encode(rgbdmsgs.rgbd_msg(f), topics.RGBD.msgtype)
    g = rgbdmsgs.rgbd_from_msg(codec.decode(data, topics.RGBD.msgtype))
    assert (g.seq, g.stamp_ns, g.depth_scale_m, g.intrinsics) == (f.seq, f.stamp_ns, f.depth_scale_m, f.intrinsics)
    assert np.array_equal(g.rgb, f.rgb) and np.array_equal(g.depth, f.depth)


def test_keyframe_round_trip_keeps_pose():
    f = _frame()
    T = pose_to_matrix(np.array([1.0, -2.0, 0.5]), np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9]))
    data = codec.encode(rgbdmsgs.keyframe_msg(7, T, f), topics.KEYFRAME.msgtype)
    kf_id, T2, g = rgbdmsgs.keyframe_from_msg(codec.decode(data, topics.KEYFRAME.msgtype))
    assert kf_id == 7 and g.seq == f.seq
    np.testing.assert_allclose(T2, T, atol=1e-12)


@pytest.mark.parametrize("topic", topics.ALL, ids=lambda t: t.name)
def test_every_topic_type_has_a_schema_for_mcap(topic):
    from rosbags.typesys import get_types_from_msg

    text = codec.msgdef(topic.msgtype)
    top = text.split("=" * 80)[0]
    parsed = get_types_from_msg(top, topic.msgtype)[topic.msgtype]
    registered = codec.typestore().fielddefs[topic.msgtype]
    assert [f[0] for f in parsed[1]] == [f[0] for f in registered[1]]


def test_size_mismatch_is_an_input_error():
    f = _frame()
    msg = rgbdmsgs.rgbd_msg(f)
    msg.camera_info.width = 64
    with pytest.raises(InputError, match="image sizes disagree"):
        rgbdmsgs.rgbd_from_msg(msg)


def test_garbage_payload_is_an_input_error():
    with pytest.raises(InputError, match="cannot decode"):
        codec.decode(b"\x00\x01\x00\x00\x05", topics.RGBD.msgtype)


def test_keys_follow_zenoh_bridge_convention():
    assert topics.RGBD.key() == "camera/rgbd"
    assert topics.RGBD.key("/robot1/") == "robot1/camera/rgbd"
    assert topics.POSE.ros_name("robot1") == "/robot1/tracker/pose"


@pytest.mark.parametrize("t, q", [((np.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),
                                  ((0.0, 0.0, 0.0), (0.0, np.inf, 0.0, 1.0))], ids=["nan", "zero", "inf"])
def test_a_pose_that_is_not_rigid_is_screened_out_of_every_message_that_carries_one(t, q):
    """The stages' checks (schemas/checks.py) refuse a non-finite translation or a zero or
    non-finite quaternion on a pose, a keyframe and a keyframe-poses message, as decoding it would."""
    from octolog.schemas.checks import checked

    good = np.eye(4)
    bad = posemsgs.pose_stamped_msg(good, 0)
    bad.pose.position.x, bad.pose.position.y, bad.pose.position.z = t
    o = bad.pose.orientation
    o.x, o.y, o.z, o.w = q
    kf = rgbdmsgs.keyframe_msg(1, good, _frame())
    kf.world_from_camera = bad.pose
    poses = posemsgs.keyframe_poses_msg({1: good, 2: good})
    poses.world_from_camera[1] = bad.pose
    for topic, msg in ((topics.POSE, bad), (topics.KEYFRAME, kf), (topics.KEYFRAME_POSES, poses)):
        data = codec.encode(msg, topic.msgtype)
        with pytest.raises(InputError, match="not a rigid transform"):
            checked(data, topic.msgtype)
    with pytest.raises(InputError, match="not a rigid transform"):
        posemsgs.pose_matrix(bad.pose)
    assert checked(codec.encode(posemsgs.pose_stamped_msg(good, 0), topics.POSE.msgtype), topics.POSE.msgtype)


def _store_hints(cls: type) -> dict[str, object]:
    """A generated message class's annotations, resolved against the type store's classes."""
    classes = {name.replace("/", "__"): c for name, c in codec.typestore().types.items()}
    names = {**classes, "np": np, "ClassVar": typing.ClassVar}
    return {k: eval(v, names) for k, v in cls.__annotations__.items() if k != "__msgtype__"}  # noqa: S307


@pytest.mark.parametrize("typename", sorted(msgtypes.OWN))
def test_own_message_classes_agree_field_by_field_with_the_type_store(typename):
    """The Protocols the builders and readers are typed with name the generated class's fields, in
    its order, with its types, and its constants."""
    generated = codec.msgtype(typename)
    protocol = msgtypes.OWN[typename]
    want = _store_hints(generated)
    have = typing.get_type_hints(protocol)
    fields = [name for name, _ in codec.typestore().fielddefs[typename][1]]
    assert [k for k in have if typing.get_origin(have[k]) is not typing.ClassVar] == fields
    assert have == want


def test_every_own_type_has_its_message_class_and_stock_classes_are_the_stores():
    store = codec.typestore()
    own = {name for name in store.types if name.startswith((codec.OWN_PACKAGE + "/", *(
        f"{pkg}/msg/{stem}" for stem, pkg in codec.VENDORED.items())))}
    assert own == set(msgtypes.OWN)
    for cls in msgtypes.STOCK:
        assert store.types[cls.__msgtype__] is cls


def test_the_stock_types_are_rosbags_jazzy_types_field_for_field():
    """schemas/stocktypes.py copies rosbags' Jazzy tables: each type, its constants and fields, and the
    schema text MCAP files carry for it, as rosbags' own Jazzy store has them."""
    from rosbags.typesys import Stores, get_typestore

    from octolog.schemas.stocktypes import FIELDDEFS

    jazzy = get_typestore(Stores.ROS2_JAZZY)
    for name, defs in FIELDDEFS.items():
        assert defs == jazzy.fielddefs[name], name
        assert codec.msgdef(name) == jazzy.generate_msgdef(name, ros_version=2)[0], name
    used = [cls.__msgtype__ for cls in msgtypes.STOCK] + [logview.POSE_ARRAY, logview.DIAGNOSTICS]
    assert set(used) <= set(FIELDDEFS)
