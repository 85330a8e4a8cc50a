"""What the calibration's and the diagnosis' figures share: names, bands, worker processes.

* :data:`LOAD_CASE_LABELS`: the load cases as the figures name them;
* :func:`dense_grid`: the moments continuous curves are drawn at;
* :func:`noise_band`: the ± 2σ band around a curve (or zero);
* :func:`plot_workers` and :func:`fork_map`: drawing many independent figures in worker
  processes, as many as the cores free (never more: a worker beside a busy core slows every
  figure down), forked from the process that holds the data;
* :func:`text_caching_canvas`: an Agg canvas that renders each distinct text once (figures
  redrawn many times repeat their tick labels and titles).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

import numpy as np

from femcal.threads import THREAD_VARIABLES, choose_threads, machine_cpus, machine_load

#: Load-case names in figures.
LOAD_CASE_LABELS = {
    "Flexion": "flexion",
    "Extension": "extension",
    "LateralBending": "lateral bending",
    "AxialRotation": "axial rotation",
}

#: Fewest figures per worker process: below, a worker costs more than it saves.
MIN_FIGURES_PER_WORKER = 8


#: Distinct texts a :func:`text_caching_canvas` keeps (then it starts afresh).
MAX_CACHED_TEXTS = 4096

_CACHING_CANVAS: Any = None


def _merged(images: list, x: int, y: int) -> list:
    """The glyph images of one text as one image (the most coverage where glyphs overlap),
    placed relative to the text's anchor ``(x, y)``: ``[(image, dx, dy, angle)]``. Rotated
    images (drawn by ``draw_text_image`` itself) stay apart."""
    if not images or any(a != 0 for _, _, _, a in images):
        return [(im, ix - x, iy - y, a) for im, ix, iy, a in images]
    left = min(ix for _, ix, _, _ in images)
    right = max(ix + im.shape[1] for im, ix, _, _ in images)
    top = min(iy - im.shape[0] for im, _, iy, _ in images)
    bottom = max(iy for _, _, iy, _ in images)
    out = np.zeros((bottom - top, right - left), dtype=np.uint8)
    for im, ix, iy, _ in images:
        h, w = im.shape
        region = out[iy - h - top : iy - top, ix - left : ix - left + w]
        np.maximum(region, im, out=region)
    return [(out, left - x, bottom - y, 0)]


def _caching_canvas_class() -> Any:
    """The Agg canvas class of :func:`text_caching_canvas` (built on first use: matplotlib is
    imported only by the figures)."""
    global _CACHING_CANVAS
    if _CACHING_CANVAS is not None:
        return _CACHING_CANVAS
    from matplotlib.backends.backend_agg import FigureCanvasAgg, RendererAgg

    class _Recorder:
        """Stands in for the Agg renderer while a text is laid out: keeps the coverage
        images of its glyphs (``draw_text_image``'s y is the image's bottom row, downwards)."""

        def __init__(self, renderer: Any) -> None:
            self.renderer, self.images = renderer, []

        def draw_text_image(self, image: Any, x: int, y: int, angle: float, gc: Any) -> None:
            self.images.append((np.array(image, dtype=np.uint8), int(x), int(y), angle))

        def __getattr__(self, name: str) -> Any:
            return getattr(self.renderer, name)

    class TextCachingRenderer(RendererAgg):
        """Agg, with each text anchored on a whole pixel and its glyph coverage kept: a text
        drawn again (same string, font, angle) is copied, not laid out and rendered again."""

        def __init__(self, width: float, height: float, dpi: float) -> None:
            super().__init__(width, height, dpi)
            self._texts: dict[tuple, list] = {}

        @property
        def texts_rendered(self) -> int:
            """The distinct texts rendered so far (each drawn again is copied)."""
            return len(self._texts)

        def draw_text(self, gc, x, y, s, prop, angle, ismath=False, mtext=None):  # noqa: ANN001
            x, y = round(x), round(y)
            if ismath:
                return super().draw_text(gc, x, y, s, prop, angle, ismath, mtext)
            key = (
                s,
                prop,
                angle,
                gc.get_antialiased(),
                None if mtext is None else str(mtext.get_fontfeatures()),
                None if mtext is None else mtext.get_language(),
            )
            images = self._texts.get(key)
            if images is None:
                recorder = _Recorder(self._renderer)
                self._renderer = recorder
                try:
                    super().draw_text(gc, x, y, s, prop, angle, ismath, mtext)
                finally:
                    self._renderer = recorder.renderer
                if len(self._texts) >= MAX_CACHED_TEXTS:
                    self._texts.clear()
                images = self._texts[key] = _merged(recorder.images, x, y)
            for image, dx, dy, a in images:
                self._renderer.draw_text_image(image, x + dx, y + dy, a, gc)
            return None

    class TextCachingCanvas(FigureCanvasAgg):
        """:class:`FigureCanvasAgg` drawing with a :class:`TextCachingRenderer`."""

        def get_renderer(self) -> Any:
            w, h = self.get_width_height(physical=True)
            key = w, h, self.figure.dpi
            if self._lastKey != key:
                self.renderer = TextCachingRenderer(w, h, self.figure.dpi)
                self._lastKey = key
            return self.renderer

    _CACHING_CANVAS = TextCachingCanvas
    return _CACHING_CANVAS


def text_caching_canvas(figure: Any) -> Any:
    """An Agg canvas for ``figure`` (it becomes ``figure.canvas``) that renders each distinct
    text once per canvas: every text is anchored on a whole pixel, and a text drawn again with
    the same string, font and angle is copied from its first rendering (a figure redrawn for
    many specimens repeats its tick labels, load-case names and legend)."""
    return _caching_canvas_class()(figure)


def dense_grid(moments: Sequence[float], q: int = 48) -> np.ndarray:
    """``q`` log-spaced moments spanning the measured grid (and every grid moment itself)."""
    m = np.asarray(moments, dtype=float)
    grid = np.geomspace(m.min(), m.max(), q)
    return np.unique(np.concatenate([grid, m]))


def noise_band(ax: Any, x: np.ndarray, centre: np.ndarray, sigma: Any, **style: Any) -> Any:
    """Fill ``centre ± 2 sigma`` over ``x`` on ``ax`` (no outline); returns the collection.

    ``sigma``: a scalar or an array like ``x``; ``style``: ``color``, ``alpha``, ``label``...
    """
    lo, hi = centre - 2 * np.asarray(sigma), centre + 2 * np.asarray(sigma)
    return ax.fill_between(x, lo, hi, lw=0, **style)


def free_cores() -> int:
    """The cores this command may keep busy: the thread count chosen when it started
    (:func:`femcal.threads.limit_threads` sets :data:`~femcal.threads.THREAD_VARIABLES`; a
    count the user set there counts too), else the cores free now."""
    for key in THREAD_VARIABLES:
        value = os.environ.get(key, "").strip()
        if value.isdigit() and int(value) > 0:
            return min(int(value), machine_cpus())
    return choose_threads(machine_cpus(), machine_load())


def plot_workers(n_figures: int, cores: int | None = None) -> int:
    """Processes to draw ``n_figures`` with: the free cores (:func:`free_cores`, or
    ``cores``), at most one per :data:`MIN_FIGURES_PER_WORKER` figures, at least 1."""
    cores = free_cores() if cores is None else int(cores)
    return max(1, min(cores, n_figures // MIN_FIGURES_PER_WORKER))


def chunks(n: int, workers: int) -> list[range]:
    """``range(n)`` cut into about ``4 * workers`` contiguous pieces (a worker that is done
    takes the next one; each piece reuses the worker's figure)."""
    size = max(1, -(-n // (4 * workers)))
    return [range(i, min(n, i + size)) for i in range(0, n, size)]


def fork_map(
    fn: Callable[[Any], Any], pieces: Sequence[Any], workers: int
) -> Iterator[tuple[Any, Any]]:
    """``(piece, fn(piece))`` for every piece, in ``workers`` processes forked from this one
    (they read what this process holds), as each finishes, the pieces taken in order; in this
    process where ``workers`` is 1 or the platform does not fork."""
    if workers < 2 or len(pieces) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        for piece in pieces:
            yield piece, fn(piece)
        return
    ctx = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
        futures = {pool.submit(fn, piece): piece for piece in pieces}
        for future in as_completed(futures):
            yield futures[future], future.result()


def progress_over(pieces: Iterable[tuple[range, Any]], total: int, desc: str, show: bool):
    """``pieces`` as they come, with a bar (stderr) over the ``total`` figures when ``show``
    (a piece that is not a range of figures, such as None, counts none)."""
    if not show or total < 2:
        yield from pieces
        return
    from tqdm.auto import tqdm

    with tqdm(total=total, desc=desc, unit="specimen") as bar:
        for piece, value in pieces:
            bar.update(len(piece) if isinstance(piece, range) else 0)
            yield piece, value
