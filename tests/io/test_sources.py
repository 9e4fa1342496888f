"""Sources and targets: a path, bytes or a stream give the same bytes, and get them back."""

import io

from service.io.sources import is_path, read_source, write_target


def test_read_source_gives_the_same_bytes_from_a_path_bytes_and_a_stream(tmp_path):
    data = b"v 0 0 0\n\x00\xff"
    (tmp_path / "f").write_bytes(data)
    stream = io.BytesIO(b"xx" + data)
    stream.read(2)  # a stream is read from where it stands
    sources = [tmp_path / "f", str(tmp_path / "f"), data, bytearray(data), memoryview(data), stream]
    assert [read_source(source) for source in sources] == [data] * len(sources)


def test_write_target_overwrites_a_path_and_appends_to_a_stream(tmp_path):
    (tmp_path / "f").write_bytes(b"old contents")
    write_target(tmp_path / "f", b"new")
    assert (tmp_path / "f").read_bytes() == b"new"
    stream = io.BytesIO()
    stream.write(b"a")
    write_target(stream, b"bc")
    assert stream.getvalue() == b"abc"
    assert is_path(tmp_path) and is_path("x") and not is_path(b"x") and not is_path(stream)
