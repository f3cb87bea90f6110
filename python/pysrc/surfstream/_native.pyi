"""Type stub of the compiled module (src/lib.rs). Heights: C-contiguous float64 arrays, um,
NaN = not measured, rows grow with y. Pitches in um. Use the ``surfstream`` API instead."""

from typing import List, Optional, Tuple

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

__version__: str

def read(path: str) -> Tuple[F64, float, float, str]: ...
def write(path: str, heights_um: F64, pitch_x_um: float, pitch_y_um: float) -> None: ...
def params(
    heights_um: F64, pitch_x_um: float, pitch_y_um: float, all: bool = False, pruning_pct: float = 5.0
) -> List[Tuple[str, float, str, str]]: ...
def level(heights_um: F64, pitch_x_um: float, pitch_y_um: float) -> F64: ...
def remove_form(
    heights_um: F64, pitch_x_um: float, pitch_y_um: float, order: int
) -> Tuple[F64, F64, List[float], float]: ...
def gaussian(heights_um: F64, pitch_x_um: float, pitch_y_um: float, cutoff_um: float) -> F64: ...
def robust_gaussian(
    heights_um: F64,
    pitch_x_um: float,
    pitch_y_um: float,
    cutoff_um: float,
    max_iterations: int = 30,
    tolerance: float = 1e-3,
) -> Tuple[F64, int, bool]: ...
def separate(
    heights_um: F64,
    pitch_x_um: float,
    pitch_y_um: float,
    method: str = "wavelet",
    wavelet: str = "sym5",
    level: Optional[str] = None,
    mode: str = "symmetric",
    cutoff_um: Optional[float] = None,
    lambda_s_um: Optional[float] = None,
) -> Tuple[F64, F64, str, List[str]]: ...
def mesh(
    path: str,
    heights_um: F64,
    pitch_x_um: float,
    pitch_y_um: float,
    tolerance: Optional[str] = None,
    epsilon_um: Optional[float] = None,
    epsilon_sq: Optional[float] = None,
    level: bool = False,
    target: Optional[str] = None,
    grid: bool = False,
    max_triangles: Optional[int] = None,
    region_px: Optional[int] = None,
    model_method: str = "balanced",
    roughness_um: Optional[F64] = None,
    remove_spikes: bool = False,
    sheet: bool = False,
    holes: bool = False,
    ascii: bool = False,
    units: Optional[str] = None,
    base_depth_um: Optional[float] = None,
    curve: bool = True,
) -> str: ...
def abbott(heights_um: F64, pitch_x_um: float, pitch_y_um: float, samples: int) -> List[Tuple[float, float]]: ...
def psd(heights_um: F64, pitch_x_um: float, pitch_y_um: float) -> List[Tuple[float, float]]: ...
def preview_png(heights_um: F64, max_side_px: int) -> Optional[Tuple[bytes, float, float]]: ...
def prep(
    heights_um: F64, pitch_x_um: float, pitch_y_um: float, steps: List[Tuple[str, str]]
) -> Tuple[F64, float, float, str]: ...
def readable_extensions() -> List[str]: ...
def height_text(v_um: float) -> str: ...
