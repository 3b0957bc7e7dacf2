# Sourced by the recipes in this folder (from the repository root): `scene NAME` prints the folder
# of a scene by its short name, generating it first where it is generated here.
#   city-N, tiny-N  the synthetic city and its tiny preset, seed N (leco scene synth), under scenes/
#   lego, fern      the NeRF datasets, at $LEGO and $FERN (default ../shared/datasets/...;
#                   docs/SCENES.md says where to get them)
#   rooftop         scenes/giza-rooftop, built from $ROOFTOP_MIRROR, a fetched mirror of
#                   Vincent7140/dataset_perso (bench/real_capture.py; no licence stated: local use)
scene() {
    local dir
    case "$1" in
        city-* | tiny-*) dir="scenes/$1"
            [ -d "$dir" ] || .venv/bin/leco scene synth --preset "${1%%-*}" --seed "${1#*-}" \
                --out "$dir" >&2 ;;
        lego) dir="${LEGO:-../shared/datasets/nerf_synthetic_lego_200}" ;;
        fern) dir="${FERN:-../shared/datasets/nerf_llff_fern}" ;;
        rooftop) dir="scenes/giza-rooftop"
            [ -d "$dir" ] || .venv/bin/python -m bench.real_capture --width 240 --out "$dir" \
                --source "${ROOFTOP_MIRROR:?a mirror of Vincent7140/dataset_perso}" >&2 ;;
        *) echo "scene: unknown scene $1 (city-N, tiny-N, lego, fern, rooftop)" >&2; return 2 ;;
    esac
    [ -d "$dir" ] || { echo "scene: $dir is missing (docs/SCENES.md)" >&2; return 2; }
    echo "$dir"
}
