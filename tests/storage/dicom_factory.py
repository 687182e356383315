"""Write small synthetic DICOM MR series for the reader tests.

The geometry is chosen here (orientation, origin, step) so the tests can
compute the expected affine independently of the reader.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid

PHI = {
    "PatientName": "Doe^Jane^Secret",
    "PatientID": "SECRET-ID-4711",
    "PatientBirthDate": "19700101",
}


def rotation(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Proper rotation Rz(yaw) @ Rx(pitch); columns = row dir, column dir, normal."""
    a, b = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rz @ rx


@dataclass
class Series:
    files: list[Path]  # in true slice order (increasing position along the normal)
    raw: np.ndarray  # (n, rows, cols) stored pixel values, true order
    row_dir: np.ndarray  # IOP[0:3] (LPS), direction of increasing column index
    col_dir: np.ndarray  # IOP[3:6] (LPS), direction of increasing row index
    normal: np.ndarray
    positions: np.ndarray  # (n, 3) IPP in LPS, true order
    pixel_spacing: tuple[float, float]  # (row spacing dy, column spacing dx)
    series_uid: str


def _ds(value: float) -> str:
    return f"{value:.6f}"


def write_series(
    folder: Path,
    *,
    n_slices: int = 6,
    rows: int = 16,
    cols: int = 12,
    yaw_deg: float = 20.0,
    pitch_deg: float = 10.0,
    origin=(-40.0, 25.0, 12.5),
    step_mm: float = 5.0,
    offsets_mm=None,
    tilt_mm_per_slice: float = 0.0,
    pixel_spacing=(0.8, 0.9),
    thickness_mm: float | None = 2.0,
    slope: float = 2.0,
    intercept: float = -10.0,
    description: str = "T2 AX",
    seed: int = 0,
    prefix: str = "IM",
) -> Series:
    """Write one series with shuffled file names and misleading InstanceNumbers."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rot = rotation(yaw_deg, pitch_deg)
    row_dir, col_dir = rot[:, 0], rot[:, 1]
    normal = np.cross(row_dir, col_dir)
    if offsets_mm is None:
        offsets_mm = np.arange(n_slices) * step_mm
    offsets_mm = np.asarray(offsets_mm, dtype=float)
    n = len(offsets_mm)
    # round positions to what is written (6 decimals) so expectations match the file
    # gantry tilt: each slice shifted along the column direction in proportion to its offset
    shift = (offsets_mm / step_mm * tilt_mm_per_slice)[:, None] * col_dir
    positions = np.round(np.asarray(origin) + offsets_mm[:, None] * normal + shift, 6)
    row_dir_w, col_dir_w = np.round(row_dir, 6), np.round(col_dir, 6)
    raw = rng.integers(0, 1000, size=(n, rows, cols)).astype(np.int16)
    series_uid = generate_uid(entropy_srcs=[f"series-{seed}-{description}"])
    study_uid = generate_uid(entropy_srcs=["study"])
    file_perm = rng.permutation(n)  # file k of true order gets name index file_perm[k]
    instance_numbers = n - np.arange(n)  # reversed: misleading on purpose
    files = []
    for k in range(n):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = MRImageStorage
        sop_uid = generate_uid(entropy_srcs=[f"sop-{seed}-{description}-{k}"])
        meta.MediaStorageSOPInstanceUID = sop_uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = MRImageStorage
        ds.SOPInstanceUID = sop_uid
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.SeriesDescription = description
        ds.Modality = "MR"
        for key, value in PHI.items():
            setattr(ds, key, value)
        ds.InstanceNumber = int(instance_numbers[k])
        ds.ImageOrientationPatient = [_ds(v) for v in (*row_dir_w, *col_dir_w)]
        ds.ImagePositionPatient = [_ds(v) for v in positions[k]]
        ds.PixelSpacing = [_ds(v) for v in pixel_spacing]
        if thickness_mm is not None:
            ds.SliceThickness = _ds(thickness_mm)
        ds.RescaleSlope = _ds(slope)
        ds.RescaleIntercept = _ds(intercept)
        ds.Rows, ds.Columns = rows, cols
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 1
        ds.PixelData = raw[k].astype("<i2").tobytes()
        f = folder / f"{prefix}{int(file_perm[k]):04d}.dcm"
        ds.save_as(f, enforce_file_format=True)
        files.append(f)
    return Series(
        files=files,
        raw=raw,
        row_dir=row_dir_w,
        col_dir=col_dir_w,
        normal=normal,
        positions=positions,
        pixel_spacing=tuple(pixel_spacing),
        series_uid=str(series_uid),
    )


def write_non_image_dicom(path: Path) -> None:
    """A DICOM file without pixel data (like a DICOMDIR)."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.1.3.10"  # Media Storage Directory
    meta.MediaStorageSOPInstanceUID = generate_uid(entropy_srcs=["dicomdir"])
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.FileSetID = "TEST"
    ds.save_as(path, enforce_file_format=True)
