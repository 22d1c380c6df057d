"""Evaluating ROS runs (gausem-ros --report): reference frames matched by stamp, argument checks."""
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from gausem_core.data import open_dataset  # noqa: E402
from gausem_ros import convert, run_all  # noqa: E402
from gausem_ros.evaluation import match_frames  # noqa: E402


def test_reference_frames_are_matched_by_stamp_in_processing_order():
    reference = open_dataset("synthetic", size=(16, 12), max_frames=4)
    stamps = [reference[2].timestamp, reference[0].timestamp + 1e-7]  # a stamp off by float round-off still matches
    assert [f.index for f in match_frames(reference, stamps)] == [2, 0]
    with pytest.raises(ValueError, match=r"1 of 2 processed frames have no reference frame .* 5\.000000"):
        match_frames(reference, [reference[1].timestamp, 5.0])


def test_report_arguments(tmp_path, capsys):
    bag = tmp_path / "bag"
    assert convert.main(["synthetic", str(bag), "--size", "16x12", "--max-frames", "1"]) == 0
    with pytest.raises(SystemExit):
        run_all.parse_arguments(["gausem-ros", str(bag), "--report", str(tmp_path / "out")])
    assert "--report with a bag needs --reference SPEC" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run_all.parse_arguments(["gausem-ros", "--report", str(tmp_path / "out")])
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    for path in (a, b):
        path.write_text("/**:\n  ros__parameters:\n    seed: 0\n")
    argv = ["gausem-ros", str(bag), "--report", "out", "--reference", "synthetic", "--ros-args", "--params-file",
            str(a), "-p", "x:=1", "--params-file", str(b)]
    ns = run_all.parse_arguments(argv)
    assert (ns.reference, str(ns.report)) == ("synthetic", "out") and run_all.params_file(argv) == str(b)
    capsys.readouterr()
    with pytest.raises(SystemExit):  # a reference that cannot be read fails before anything is replayed
        run_all.parse_arguments(["gausem-ros", str(bag), "--report", "out", "--reference", f"tum:{tmp_path / 'no'}"])
    assert "--report: cannot read the reference" in capsys.readouterr().err
