"""A rosbag2 recording given as its folder: the MCAP file inside it, or why it cannot be read.

`ros2 bag record -s mcap -o NAME` writes a folder, NAME/metadata.yaml beside NAME/NAME_0.mcap,
and labs pass that folder on as "the recording". Its single MCAP file is what we read; what we
cannot read (a sqlite3 bag, file-compressed or per-message-compressed storage, a bag split
into several files) is refused with the rosbag2 command that makes it readable, so nothing is
guessed and nothing lost.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from afm_core.checks import few
from afm_core.recording.errors import RecordingError

METADATA = "metadata.yaml"
MCAP_SUFFIX = ".mcap"
# `ros2 bag convert` writes one uncompressed MCAP file from any bag rosbag2 can read
CONVERT_HINT = (
    "`ros2 bag convert -i {folder} -o out.yaml` with out.yaml holding "
    "`output_bags: [{{uri: merged, storage_id: mcap}}]` writes one MCAP file we read"
)


def recording_file(path: Path) -> Path:
    """`path` itself unless it is a folder; for a rosbag2 folder, its one MCAP file."""
    if not path.is_dir():
        return path
    metadata = path / METADATA
    if metadata.is_file():
        files = _listed_files(path, metadata)
        if len(files) > 1:
            raise RecordingError(
                f"recording {str(path)!r} is split into {len(files)} files ({few(files, 3)}); "
                "give one of them, or merge them: " + CONVERT_HINT.format(folder=path)
            )
    else:
        files = sorted(p.name for p in path.glob(f"*{MCAP_SUFFIX}") if p.is_file())
        if len(files) != 1:
            held = (
                f"{len(files)} {MCAP_SUFFIX} files ({few(files, 3)})"
                if files
                else f"no {MCAP_SUFFIX} file"
            )
            raise RecordingError(
                f"recording {str(path)!r} is a folder with no {METADATA} and {held}; give "
                "the recording file itself"
            )
    # older rosbag2 wrote the folder's own name in front of each listed file
    for found in (_inside(path, files[0]), path / Path(files[0]).name):
        if found.is_file():
            return found
    raise RecordingError(
        f"recording {str(path)!r}: {METADATA} lists {files[0]!r}, which is not in the folder"
    )


def _inside(folder: Path, listed: str) -> Path:
    """`folder / listed`, refused unless it resolves inside the folder: metadata.yaml comes with
    the recording, and a listed path that is absolute or climbs out with `..` (or a symlink
    that points out) would have us open any file, past the roots a node may read from."""
    found = folder / listed
    if not found.resolve().is_relative_to(folder.resolve()):
        raise RecordingError(
            f"recording {str(folder)!r}: {METADATA} lists {listed!r}, which is outside the "
            "folder; a rosbag2 folder lists only its own files"
        )
    return found


def _listed_files(folder: Path, metadata: Path) -> list[str]:
    try:
        info = (yaml.safe_load(metadata.read_text()) or {})["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier", ""))
        compression = str(info.get("compression_mode", "") or "")
        listed = info.get("relative_file_paths", [])
        if not isinstance(listed, list):  # a string would count its characters as files
            raise TypeError(f"relative_file_paths is a {type(listed).__name__}, not a list")
        files = [str(f) for f in listed]
    except (yaml.YAMLError, KeyError, TypeError, AttributeError, OSError) as exc:
        raise RecordingError(
            f"recording {str(folder)!r}: {METADATA} is not rosbag2 metadata ({exc})"
        ) from None
    if storage != "mcap":
        raise RecordingError(
            f"recording {str(folder)!r} is a rosbag2 bag in {storage or 'unnamed'} storage, "
            "not MCAP; " + CONVERT_HINT.format(folder=folder)
        )
    if compression.upper() not in ("", "NONE"):
        raise RecordingError(
            f"recording {str(folder)!r} is compressed by rosbag2 (compression_mode "
            f"{compression}); " + CONVERT_HINT.format(folder=folder)
        )
    if not files:
        raise RecordingError(f"recording {str(folder)!r}: {METADATA} lists no file")
    return files
