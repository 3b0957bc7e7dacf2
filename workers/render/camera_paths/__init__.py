"""Camera-path kinds for renders: each a schema that builds its path (base.py), in its own file,
listed in one registry (registry.py). The render schema, the CLI and the dashboard read the
registry; no other module names a kind. The schemas import no PyTorch; a path is built
(model/scenes/camera_paths.py) where a render runs."""
