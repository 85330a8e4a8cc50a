"""Obtain the study's published FE dataset: from a local mirror or by download, SHA-256 pinned.

Every file is written to a temporary file next to its destination, its SHA-256 is checked
against :data:`MANIFEST`, and only then is it moved into place with :func:`os.replace`; a
partial or corrupted transfer therefore never becomes an output.
"""

from __future__ import annotations

import hashlib
import logging
import os
import urllib.parse
import urllib.request
import uuid
from collections.abc import Callable, Iterator, Mapping
from http.client import HTTPException
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from femcal.errors import ChecksumError, ConfigError, DataSourceError

logger = logging.getLogger(__name__)

#: GitHub repository of the reference study.
STUDY_REPOSITORY = "matanat/IVD-CalibNN"
#: The pinned commit of the study's repository whose ``datasets/`` folder is used.
STUDY_COMMIT = "0754ea14c757cf6e72fade7cc934d3dbf22fdafa"
#: Base address of the raw files; a file's URL is ``BASE_URL + relpath``.
BASE_URL = f"https://raw.githubusercontent.com/{STUDY_REPOSITORY}/{STUDY_COMMIT}/datasets/"
#: Environment variable naming a local folder that holds ``Large/``, ``Small/``, ``Test/``.
MIRROR_ENV_VAR = "FEMCAL_DATA_MIRROR"

#: SHA-256 of every published data file, keyed by its path relative to ``datasets/``.
MANIFEST: dict[str, str] = {
    # Large: 1024 Latin-hypercube configurations.
    "Large/MaterialConfigurations.csv": (
        "0909744ef87801dff0791bb93e5fb611786551276327081652f97b0517e8b177"
    ),
    "Large/ParameterBounds.csv": (
        "443eadc856923c4883c3d37599bfc5bf724cef853ea1cdf8d032012087d2b23f"
    ),
    "Large/ROM_Results_Flexion_wMoment.csv": (
        "3f5c2c77cdebf39819bf7e03546ee6360ad2dace8c9e58e6b337ecb49f58a7dc"
    ),
    "Large/ROM_Results_Extension_wMoment.csv": (
        "47f2725a66da0b463136d27b6384a862e26f3e5c06bb44bb5717e415223631f5"
    ),
    "Large/ROM_Results_LateralBending_wMoment.csv": (
        "9c7ef379b68f0eab0526437a51c469561a6b91252a067951f64a273c07aa6866"
    ),
    "Large/ROM_Results_AxialRotation_wMoment.csv": (
        "469d1b6698f25347df7826f3899b3cbe121c829754c1f1262b17df52c0de1459"
    ),
    "Large/IDP_Results_Flexion_wMoment.csv": (
        "fae9503a18a2d1fcd8ebb209c8bee7635271d2c2c89fa3c1c8b277600216bf7a"
    ),
    "Large/IDP_Results_Extension_wMoment.csv": (
        "fa5385e06925238b9f15bdc0cfd9bb6f63fd235b066f9eb97aa890a7bac20d9a"
    ),
    "Large/IDP_Results_LateralBending_wMoment.csv": (
        "1e64e64ab51f69a05be6aa56c1c85080088bc04fbf5a2b58fed5c913dc699f75"
    ),
    "Large/IDP_Results_AxialRotation_wMoment.csv": (
        "b964db07852c87bfcf36fd3177a9ea3356ba15df66ab1522190f6ba3155188b6"
    ),
    # Small: 128 Latin-hypercube configurations.
    "Small/MaterialConfigurations_Small_128.csv": (
        "74cf34bb5c420d592f05aebb2b76841395ca675be357db35713e0eefecf8db60"
    ),
    "Small/ParameterBounds.csv": (
        "443eadc856923c4883c3d37599bfc5bf724cef853ea1cdf8d032012087d2b23f"
    ),
    "Small/ROM_Results_Flexion_Small_128_wMoment.csv": (
        "c94ed2793c5bd5288813b60e1d54bdb4e5f0eb6cda53c092d4fef94a89959bbd"
    ),
    "Small/ROM_Results_Extension_Small_128_wMoment.csv": (
        "054915b138b72db8f522ddf4ab35a66a13537a34f1f2663c3bd5871e22f13499"
    ),
    "Small/ROM_Results_LateralBending_Small_128_wMoment.csv": (
        "057b69d638a9b88632a5ddf523b5aea47991c7c286d03dc5f55383d97ab2fd35"
    ),
    "Small/ROM_Results_AxialRotation_Small_128_wMoment.csv": (
        "38e2c23242869d760e462b9904c4400d23009ed19abdfc28c90be3e2c7989a9c"
    ),
    "Small/IDP_Results_Flexion_Small_128_wMoment.csv": (
        "23a19ba9d86acab05c771524d80d596ddbafe45aa9ce6b95b5717c165e0255f3"
    ),
    "Small/IDP_Results_Extension_Small_128_wMoment.csv": (
        "dbf24846c4a801aae43cdba5003177b1880c9859de523d4585d8e10cf43ffe34"
    ),
    "Small/IDP_Results_LateralBending_Small_128_wMoment.csv": (
        "c5042684e06082e231eb898db3716f297b8caa77114a399e5a1675c3a18a6fa7"
    ),
    "Small/IDP_Results_AxialRotation_Small_128_wMoment.csv": (
        "ad211ead5da7622a8ffaf89113c4105bd21d784f3c2b5a4191c03c26754e5819"
    ),
    # Test: 64 random configurations.
    "Test/MaterialConfigurations_TestData_64.csv": (
        "1b1d15c768f074b5f5985ce9d3c1b4588748e0a5b449a644dda7600939704b0c"
    ),
    "Test/ParameterBounds.csv": (
        "ca5a47bd4c4722a56d517170a09805a259262e96d7a7ded49ef6937e1eb2dc68"
    ),
    "Test/ROM_Results_Flexion_TestData_64_wMoment.csv": (
        "8cb584d6cded0a4b206e8f4bcf33e7e6528530d7fe317e87ebdff9ea1539e8c3"
    ),
    "Test/ROM_Results_Extension_TestData_64_wMoment.csv": (
        "08a1dae1ad382becc6036a4a916d014872e079e4dff0ab80b261fb1a0a74296d"
    ),
    "Test/ROM_Results_LateralBending_TestData_64_wMoment.csv": (
        "a505dbdfad1e52a54e9edb499bee08feb8c59fa416b1ad67cf8c2b755a2e87ad"
    ),
    "Test/ROM_Results_AxialRotation_TestData_64_wMoment.csv": (
        "32327b9309c956131e02850a81f62a354cdec75fb2b5d647e267761d5b1b3815"
    ),
    "Test/IDP_Results_Flexion_TestData_64_wMoment.csv": (
        "c0c629fae1c1ac40ab064fe5a4b3e3ef3d3376d26d31e5cd1de6dc836d727c80"
    ),
    "Test/IDP_Results_Extension_TestData_64_wMoment.csv": (
        "25a989990ee67c4692934af47a0618bcda14454b929f41ba136f4256b0f6bef7"
    ),
    "Test/IDP_Results_LateralBending_TestData_64_wMoment.csv": (
        "cfcad48eacd696b44c1e1be9ee2a4ace5d518f9c721968f4b8dc87834d688fab"
    ),
    "Test/IDP_Results_AxialRotation_TestData_64_wMoment.csv": (
        "87e29ef47eaf3adf8ef6330c674461defc15deefae36678b76d4f056c9b9d7a3"
    ),
}

_CHUNK = 1 << 16


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's bytes.

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    str
        64 lower-case hexadecimal digits.
    """
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(_CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


def mirror_from_env(environ: Mapping[str, str] = os.environ) -> Path | None:
    """The local mirror folder named by ``FEMCAL_DATA_MIRROR``, if any.

    Parameters
    ----------
    environ : mapping of str to str, optional
        Environment to read (defaults to :data:`os.environ`).

    Returns
    -------
    Path or None
        The folder, or None when the variable is unset or empty.

    Raises
    ------
    DataSourceError
        The variable is set but does not name an existing directory.
    """
    value = environ.get(MIRROR_ENV_VAR, "").strip()
    if not value:
        return None
    path = Path(value).expanduser()
    if not path.is_dir():
        raise DataSourceError(
            f"{MIRROR_ENV_VAR}={value!r} is not a directory. Set {MIRROR_ENV_VAR} to the folder "
            "holding Large/, Small/ and Test/ of the study's dataset, or unset it to download "
            "the files."
        )
    return path


def _check_relpath(relpath: str) -> PurePosixPath:
    rel = PurePosixPath(relpath)
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise ConfigError(
            f"Manifest entry {relpath!r} must be a relative path inside the dataset folder "
            "(no leading '/', no '..')."
        )
    return rel


def _stream_to_temp(source: BinaryIO, target: Path) -> tuple[Path, str]:
    """Copy ``source`` into a new temporary file next to ``target``; return it and its SHA-256."""
    target.parent.mkdir(parents=True, exist_ok=True)
    # A unique name created with the usual permissions (mkstemp would make it owner-only).
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.part")
    digest = hashlib.sha256()
    try:
        with open(tmp, "xb") as out:
            for chunk in iter(lambda: source.read(_CHUNK), b""):
                digest.update(chunk)
                out.write(chunk)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp, digest.hexdigest()


def _open_mirror(mirror: Path, relpath: str) -> Callable[[], BinaryIO]:
    src = mirror.joinpath(*PurePosixPath(relpath).parts)

    def opener() -> BinaryIO:
        if not src.is_file():
            raise DataSourceError(
                f"The data file {relpath} is missing in the mirror {mirror} (looked for {src}). "
                f"Set {MIRROR_ENV_VAR} to the folder holding Large/, Small/ and Test/ of the "
                "study's dataset, or unset it to download the files."
            )
        return open(src, "rb")

    return opener


def _open_url(url: str, timeout: float) -> Callable[[], BinaryIO]:
    def opener() -> BinaryIO:
        try:
            return urllib.request.urlopen(url, timeout=timeout)
        except (OSError, HTTPException, ValueError) as exc:
            raise _download_error(url, exc) from exc

    return opener


def _download_error(url: str, exc: BaseException) -> DataSourceError:
    return DataSourceError(
        f"Downloading {url} failed: {type(exc).__name__}: {exc}. Check the network connection "
        f"(and proxy settings), then retry; or set {MIRROR_ENV_VAR} to a local folder holding "
        "Large/, Small/ and Test/ of the study's dataset."
    )


def _fetch_one(
    relpath: str,
    expected: str,
    target: Path,
    opener: Callable[[], BinaryIO],
    origin: str,
    *,
    from_mirror: bool,
) -> None:
    """Obtain one file through ``opener`` into ``target`` via a verified temporary file."""
    with opener() as source:
        try:
            tmp, received = _stream_to_temp(source, target)
        except (OSError, HTTPException) as exc:
            if from_mirror:
                raise DataSourceError(
                    f"Reading {relpath} from the mirror ({origin}) failed: {exc}. Check the file "
                    f"and its permissions, or unset {MIRROR_ENV_VAR} to download the files."
                ) from exc
            raise _download_error(origin, exc) from exc
        remaining = getattr(source, "length", None)  # HTTP: bytes announced but not received
        if isinstance(remaining, int) and remaining > 0:
            tmp.unlink(missing_ok=True)
            raise _download_error(
                origin, ConnectionError(f"transfer ended {remaining} bytes early")
            )
    if received != expected.lower():
        tmp.unlink(missing_ok=True)
        if from_mirror:
            fix = (
                f"The mirror does not hold the study's files at commit {STUDY_COMMIT}: point "
                f"{MIRROR_ENV_VAR} at an unmodified copy of that commit's datasets/ folder, or "
                "unset it to download the files."
            )
        else:
            fix = (
                "The transfer was corrupted or the server does not serve the study's pinned "
                f"commit {STUDY_COMMIT}: re-run to re-download, and check base_url."
            )
        raise ChecksumError(
            f"SHA-256 mismatch for {relpath} from {origin}: expected {expected.lower()}, "
            f"received {received}. Nothing was written to {target}. {fix}"
        )
    try:
        os.replace(tmp, target)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


def fetch_dataset(
    dest: Path,
    *,
    mirror: Path | None = None,
    base_url: str = BASE_URL,
    manifest: Mapping[str, str] = MANIFEST,
    timeout: float = 60.0,
    progress: bool = False,
) -> list[Path]:
    """Make ``dest`` hold every file of ``manifest`` with its pinned SHA-256.

    A file already present with the right hash is kept untouched. Otherwise it is copied
    from ``mirror / relpath`` (when ``mirror`` is given) or downloaded from
    ``base_url + relpath``, written to a temporary file in the destination folder, checked
    and moved into place atomically. On any failure the temporary file is removed.

    Parameters
    ----------
    dest : Path
        Folder that receives ``Large/``, ``Small/`` and ``Test/``.
    mirror : Path, optional
        Local folder with the same layout (see :func:`mirror_from_env`); no download then.
    base_url : str, optional
        Prefix of the download addresses (the study's pinned commit by default).
    manifest : mapping of str to str, optional
        Relative path (POSIX separators) -> expected SHA-256.
    timeout : float, optional
        Socket timeout of a download, in seconds.
    progress : bool, optional
        Show a tqdm progress bar over the files.

    Returns
    -------
    list of Path
        ``dest / relpath`` for every manifest entry, in manifest order.

    Raises
    ------
    DataSourceError
        A file is missing in the mirror, or a download failed.
    ChecksumError
        A copied or downloaded file does not have its pinned SHA-256.
    """
    dest = Path(dest)
    mirror = Path(mirror) if mirror is not None else None
    entries: list[tuple[str, str, Path]] = []
    for relpath, expected in manifest.items():
        rel = _check_relpath(relpath)
        entries.append((relpath, expected.lower(), dest.joinpath(*rel.parts)))

    iterator: Iterator[tuple[str, str, Path]] = iter(entries)
    if progress:
        from tqdm.auto import tqdm

        iterator = iter(tqdm(entries, desc="fetch", unit="file"))

    n_kept = n_new = 0
    for relpath, expected, target in iterator:
        if target.is_file():
            if sha256_file(target) == expected:
                logger.debug("%s present with the right SHA-256; kept.", target)
                n_kept += 1
                continue
            logger.warning("%s has the wrong SHA-256; fetching it again.", target)
        if mirror is not None:
            origin = str(mirror.joinpath(*PurePosixPath(relpath).parts))
            opener = _open_mirror(mirror, relpath)
        else:
            origin = base_url + urllib.parse.quote(relpath)
            opener = _open_url(origin, timeout)
        logger.info("Fetching %s from %s", relpath, origin)
        _fetch_one(relpath, expected, target, opener, origin, from_mirror=mirror is not None)
        n_new += 1
    logger.info("Dataset in %s: %d file(s) fetched, %d already present.", dest, n_new, n_kept)
    return [target for _, _, target in entries]
