"""Obtain the study's published FE dataset: from a local mirror or by download, SHA-256 pinned.

The files are a :mod:`pooch` registry (:data:`MANIFEST`: relative path -> SHA-256). Pooch
writes every file to a temporary file next to its destination, checks its SHA-256 and only
then moves it into place; a partial or corrupted transfer therefore never becomes an output.
A local mirror (``FEMCAL_DATA_MIRROR``) is read by a copying downloader, without any network
access, and is checked against the same hashes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import urllib.parse
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path, PurePosixPath

import pooch

from femcal.errors import ChecksumError, ConfigError, DataSourceError, FemcalError

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
    return pooch.file_hash(str(path), alg="sha256").lower()


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
    return _mirror_folder(Path(value).expanduser(), f"{MIRROR_ENV_VAR}={value!r}")


def _mirror_folder(path: Path, named: str) -> Path:
    """``path`` if it is a directory; ``named`` says where it came from in the error."""
    if not path.is_dir():
        raise DataSourceError(
            f"{named} is not a directory. Give (or set {MIRROR_ENV_VAR} to) the folder holding "
            "Large/, Small/ and Test/ of the study's dataset, or unset it to download the files."
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


class _Recording:
    """A pooch downloader wrapper that remembers the SHA-256 of what each call wrote.

    Pooch reports a hash mismatch as a bare :class:`ValueError`; the recorded hash lets
    :func:`fetch_dataset` raise a :class:`ChecksumError` that names the received hash.
    """

    def __init__(self, inner: Callable[[str, str, pooch.Pooch | None], None]) -> None:
        self.inner = inner
        self.received: dict[str, str] = {}

    def __call__(self, url: str, output_file: str, pooch_: pooch.Pooch | None) -> None:
        self.inner(url, output_file, pooch_)
        self.received[url] = sha256_file(output_file)


class _MirrorCopy:
    """A pooch downloader that copies a local file: the "URL" of a mirror file is its path.

    No network access: the file is read from the mirror folder only.
    """

    def __init__(self, mirror: Path) -> None:
        self.mirror = mirror

    def __call__(self, url: str, output_file: str, pooch_: pooch.Pooch | None) -> None:
        src = Path(url)
        if not src.is_file():
            relpath = src.relative_to(self.mirror).as_posix()
            raise DataSourceError(
                f"The data file {relpath} is missing in the mirror {self.mirror} (looked for "
                f"{src}). Set {MIRROR_ENV_VAR} to the folder holding Large/, Small/ and Test/ "
                "of the study's dataset, or unset it to download the files."
            )
        try:
            shutil.copyfile(src, output_file)
        except OSError as exc:
            raise DataSourceError(
                f"Reading {src} from the mirror failed: {exc}. Check the file and its "
                f"permissions, or unset {MIRROR_ENV_VAR} to download the files."
            ) from exc


def _download_error(url: str, exc: BaseException) -> DataSourceError:
    return DataSourceError(
        f"Downloading {url} failed: {type(exc).__name__}: {exc}. Check the network connection "
        f"(and proxy settings), then retry; or set {MIRROR_ENV_VAR} to a local folder holding "
        "Large/, Small/ and Test/ of the study's dataset."
    )


def _checksum_error(
    relpath: str, origin: str, expected: str, received: str, target: Path, *, from_mirror: bool
) -> ChecksumError:
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
    return ChecksumError(
        f"SHA-256 mismatch for {relpath} from {origin}: expected {expected}, "
        f"received {received}. Nothing was written to {target}. {fix}"
    )


@contextlib.contextmanager
def _quiet_pooch() -> Iterator[None]:
    """Silence pooch's own stderr logger below WARNING; femcal logs the transfers itself."""
    pooch_logger = pooch.get_logger()
    level = pooch_logger.level
    pooch_logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        pooch_logger.setLevel(level)


def _usual_file_mode() -> int:
    """The mode a newly created file gets under the current umask (pooch's are 0o600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


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

    ``dest`` is the local storage of a :func:`pooch.create` registry built from
    ``manifest``. A file already present with the right hash is kept untouched. Otherwise
    it is copied from ``mirror / relpath`` (when ``mirror`` is given; no network access
    then) or downloaded from ``base_url + relpath``; pooch writes it to a temporary file in
    the destination folder, checks it and moves it into place. On any failure the temporary
    file is removed.

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
    ConfigError
        A manifest entry is not a relative path inside the dataset folder.
    DataSourceError
        The mirror is not a directory, a file is missing in the mirror, or a download failed.
    ChecksumError
        A copied or downloaded file does not have its pinned SHA-256.
    """
    dest = Path(dest)
    from_mirror = mirror is not None
    entries: list[tuple[str, str, Path]] = []
    for relpath, expected in manifest.items():
        rel = _check_relpath(relpath)
        entries.append((relpath, expected.lower(), dest.joinpath(*rel.parts)))

    if mirror is not None:
        mirror = Path(mirror).expanduser()
        _mirror_folder(mirror, f"The mirror {mirror}")
        urls = {rel: str(mirror.joinpath(*PurePosixPath(rel).parts)) for rel, _, _ in entries}
        downloader = _Recording(_MirrorCopy(mirror))
    else:
        urls = {rel: base_url + urllib.parse.quote(rel) for rel, _, _ in entries}
        downloader = _Recording(pooch.HTTPDownloader(timeout=timeout, progressbar=False))
    registry = pooch.create(
        path=dest,
        base_url=base_url,
        registry={rel: f"sha256:{expected}" for rel, expected, _ in entries},
        urls=urls,
        retry_if_failed=0,
    )

    iterator: Iterator[tuple[str, str, Path]] = iter(entries)
    if progress:
        from tqdm.auto import tqdm

        iterator = iter(tqdm(entries, desc="fetch", unit="file"))

    mode = _usual_file_mode()

    def record(fname: str, action: str, _pooch: pooch.Pooch) -> str:
        """Pooch processor: a new file gets the usual permissions; returns pooch's action."""
        if action != "fetch":
            os.chmod(fname, mode)
        return action

    actions: list[str] = []
    with _quiet_pooch():
        for relpath, expected, target in iterator:
            origin = urls[relpath]
            try:
                action = registry.fetch(relpath, processor=record, downloader=downloader)
            except FemcalError:
                raise
            except ValueError as exc:  # pooch's hash mismatch
                received = downloader.received.get(origin)
                if received is None or received == expected:
                    raise
                raise _checksum_error(
                    relpath, origin, expected, received, target, from_mirror=from_mirror
                ) from exc
            except OSError as exc:  # requests' errors are OSErrors
                if from_mirror:
                    raise
                raise _download_error(origin, exc) from exc
            actions.append(action)
            if action == "fetch":
                logger.debug("%s present with the right SHA-256; kept.", target)
            elif action == "update":
                logger.warning("%s had the wrong SHA-256; fetched again from %s.", target, origin)
            else:
                logger.info("Fetched %s from %s", relpath, origin)
    n_kept = actions.count("fetch")
    logger.info(
        "Dataset in %s: %d file(s) fetched, %d already present.",
        dest,
        len(actions) - n_kept,
        n_kept,
    )
    return [target for _, _, target in entries]
