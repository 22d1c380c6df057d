"""The node's ``classes`` parameter reads class tables as the datasets do (one reader for every format)."""
import pytest

pytest.importorskip("rclpy")

from gausem_ros.nodes.common import class_table  # noqa: E402


@pytest.mark.parametrize("name, text", [
    ("classes.txt", "0 floor 0 0 0\n1 wall 10 20 30\n"),
    ("classes.json", '{"0": "floor", "1": {"name": "wall", "color": [10, 20, 30]}}'),
    ("classes.json", '{"classes": [{"id": 1, "name": "wall", "color": [10, 20, 30]}, {"id": 0, "name": "floor"}]}'),
])
def test_the_classes_parameter_reads_every_class_table_format(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    table = class_table(str(path))
    assert table.names == ("floor", "wall") and table.colors[1].tolist() == [10, 20, 30]


def test_an_unknown_classes_value_is_named():
    with pytest.raises(ValueError, match="neither a built-in table"):
        class_table("no_such_table")
