"""Decode one episode of one camera from an mp4 with PyAV, frame-exactly.

Why not lerobot's decoder: `LeRobotDataset.__getitem__` reopens the file and seeks once per item
(docs/measured.md); an episode is a contiguous span of the file, so one seek to the keyframe before
it and one sequential decode gives every frame at the decoder's full speed (AV1 via libdav1d).

Frames are matched to the episode by presentation time: frame k is the one at
`from_timestamp + k / fps` within a tolerance of half a frame period, which is what lerobot does with
its query timestamps, minus the per-item seek.
"""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np

from graftcache.errors import DatasetError


def decode_span(
    path: Path,
    from_timestamp: float,
    length: int,
    fps: float,
    *,
    episode: int,
    shape: tuple[int, int, int],
    threads: int = 1,
) -> np.ndarray:
    """uint8 [length, H, W, 3] RGB: the `length` frames starting at `from_timestamp` seconds into `path`.

    `threads` is FFmpeg's decoder thread count (1 in data workers, 0 lets FFmpeg choose).
    """
    tol = 0.5 / fps
    last = from_timestamp + (length - 1) / fps
    out = np.empty((length, *shape), dtype=np.uint8)
    found = np.zeros(length, dtype=bool)
    try:
        container = av.open(str(path))
    except FileNotFoundError:
        raise DatasetError(f"{path}: video file missing (episode {episode})") from None
    except av.FFmpegError as e:
        raise DatasetError(f"{path}: cannot open video ({_reason(e)}): episode {episode} frame 0 "
                           "is unreadable") from None
    with container:
        if not container.streams.video:
            raise DatasetError(f"{path}: no video stream (episode {episode})")
        stream = container.streams.video[0]
        stream.codec_context.thread_count = threads
        end = _duration_s(stream, container)
        if from_timestamp < -tol or (end is not None and last > end - 1 / fps + tol):
            raise DatasetError(
                f"{path}: episode {episode} needs frames at {from_timestamp:.3f}..{last:.3f} s but the video "
                f"holds 0..{(end or 0) - 1 / fps:.3f} s (timestamps outside the video)")
        if (stream.codec_context.height, stream.codec_context.width) != shape[:2]:
            raise DatasetError(f"{path}: frames are {stream.codec_context.height}x{stream.codec_context.width}, "
                               f"info.json declares {shape[0]}x{shape[1]} (episode {episode})")
        try:
            container.seek(int(from_timestamp / stream.time_base), stream=stream, backward=True)
            for frame in container.decode(stream):
                k = round((frame.time - from_timestamp) * fps)
                if k >= length:
                    break
                if k < 0 or found[k] or abs(frame.time - from_timestamp - k / fps) > tol:
                    continue
                out[k] = frame.to_ndarray(format="rgb24")
                found[k] = True
                if k == length - 1:
                    break
        except av.FFmpegError as e:
            first = int(np.argmin(found)) if not found.all() else length
            raise DatasetError(f"{path}: corrupt video ({_reason(e)}): episode {episode} frame {first} "
                               f"(t={from_timestamp + first / fps:.3f} s) failed to decode") from None
    if not found.all():
        first = int(np.argmin(found))
        raise DatasetError(f"{path}: short video: episode {episode} frame {first} "
                           f"(t={from_timestamp + first / fps:.3f} s) is missing; "
                           f"decoded {int(found.sum())}/{length} frames")
    return out


def _reason(e: av.FFmpegError) -> str:
    """FFmpeg's own words without the file name it repeats."""
    return e.strerror or type(e).__name__


def _duration_s(stream: av.video.stream.VideoStream, container: av.container.InputContainer) -> float | None:
    """Length of the stream in seconds from the container header, when it declares one."""
    if stream.duration is not None:
        return float(stream.duration * stream.time_base)
    if container.duration is not None:
        return container.duration / av.time_base
    return None
