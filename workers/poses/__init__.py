"""Poses for a folder of photos: COLMAP's structure from motion (pycolmap) in a process of its own,
written as a COLMAP model beside the photos, which the COLMAP scene reader loads.

photos.py checks and describes the photos (EXIF focal length and GPS: exif.py, geodesy.py),
pairs.py picks the matcher and the image pairs, pipeline.py runs the stages (features, matching,
mapping, alignment, export) and resumes from the last one finished, process.py runs the pipeline in
a child process with limits, progress and cancelling. settings.py is the one schema of a poses job,
from `leco scene poses` and the API down to the pipeline. pycolmap is imported only in the child."""
