from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MarkerFrame(_message.Message):
    __slots__ = ("model_id", "frame", "markers", "marker_count", "outputs", "clamp", "half")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    MARKERS_FIELD_NUMBER: _ClassVar[int]
    MARKER_COUNT_FIELD_NUMBER: _ClassVar[int]
    OUTPUTS_FIELD_NUMBER: _ClassVar[int]
    CLAMP_FIELD_NUMBER: _ClassVar[int]
    HALF_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    frame: int
    markers: _containers.RepeatedScalarFieldContainer[float]
    marker_count: int
    outputs: _containers.RepeatedScalarFieldContainer[str]
    clamp: bool
    half: bool
    def __init__(self, model_id: _Optional[str] = ..., frame: _Optional[int] = ..., markers: _Optional[_Iterable[float]] = ..., marker_count: _Optional[int] = ..., outputs: _Optional[_Iterable[str]] = ..., clamp: bool = ..., half: bool = ...) -> None: ...

class Map(_message.Message):
    __slots__ = ("height", "width", "channels", "data", "half")
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    CHANNELS_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    HALF_FIELD_NUMBER: _ClassVar[int]
    height: int
    width: int
    channels: int
    data: bytes
    half: bool
    def __init__(self, height: _Optional[int] = ..., width: _Optional[int] = ..., channels: _Optional[int] = ..., data: _Optional[bytes] = ..., half: bool = ...) -> None: ...

class MeshFrame(_message.Message):
    __slots__ = ("frame", "vertex_count", "vertices", "vertices_detailed", "faces", "displacement", "albedo", "normal_map", "clamped", "latency_ms")
    FRAME_FIELD_NUMBER: _ClassVar[int]
    VERTEX_COUNT_FIELD_NUMBER: _ClassVar[int]
    VERTICES_FIELD_NUMBER: _ClassVar[int]
    VERTICES_DETAILED_FIELD_NUMBER: _ClassVar[int]
    FACES_FIELD_NUMBER: _ClassVar[int]
    DISPLACEMENT_FIELD_NUMBER: _ClassVar[int]
    ALBEDO_FIELD_NUMBER: _ClassVar[int]
    NORMAL_MAP_FIELD_NUMBER: _ClassVar[int]
    CLAMPED_FIELD_NUMBER: _ClassVar[int]
    LATENCY_MS_FIELD_NUMBER: _ClassVar[int]
    frame: int
    vertex_count: int
    vertices: bytes
    vertices_detailed: bytes
    faces: bytes
    displacement: Map
    albedo: Map
    normal_map: Map
    clamped: float
    latency_ms: float
    def __init__(self, frame: _Optional[int] = ..., vertex_count: _Optional[int] = ..., vertices: _Optional[bytes] = ..., vertices_detailed: _Optional[bytes] = ..., faces: _Optional[bytes] = ..., displacement: _Optional[_Union[Map, _Mapping]] = ..., albedo: _Optional[_Union[Map, _Mapping]] = ..., normal_map: _Optional[_Union[Map, _Mapping]] = ..., clamped: _Optional[float] = ..., latency_ms: _Optional[float] = ...) -> None: ...
