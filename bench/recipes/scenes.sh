# Sourced by the recipes in this folder (from the repository root): `scene NAME` prints the folder
# of a scene by its short name (city-N, village-N, tiny-N, lego, fern, rooftop), generating it
# first where it is generated here. bench/scenes.py says where each lives.
scene() {
    .venv/bin/python -m bench.scenes "$1"
}
