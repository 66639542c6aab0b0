#!/usr/bin/env bash
# Train, measure and ship one family's model into ngp_mi/pretrained/FAMILY (the commands the README
# quotes for the shipped models). Every step resumes or reuses what a killed run left, so running it
# again continues where it stopped.
#
#   scripts/ship-model.sh chair|car [MAP_STEPS] [SPECULAR_STEPS]
#
# MAP_STEPS / SPECULAR_STEPS cut the `cpu` recipe (4,000 / 1,500) to what the machine's time allows;
# the card records the steps taken. The shape prior and the map networks share nothing, so they
# train side by side, one CPU thread each. SHAPE_FROM=MODEL (a shipped name or a model folder)
# keeps that model's shape prior and re-trains the maps only, on all the cores. MAPS_FROM=RUN (a maps run that reached
# MAP_STEPS, or a model folder / shipped name) keeps its map networks and trains the later stages only (the recipe's
# [encoder] stage, which refits E_da, and G_sp^real), into maps_FAMILY_sp; SEED=N sets [train] seed (the shipped
# chair and car maps: SEED=1; the chair's encoder and G_sp^real stages SEED=1, the car's re-trained stage SEED=2;
# chosen on other shapes, bench/RESULTS.md). SPECULAR_FROM=MODEL ships that model's G_sp^real instead of the run's
# (export-model --specular-from; it must have been trained on the same G_n and G_da: the shipped chair's); the
# run's evaluate / compare figures on the card are then its own stage's, so measure the model folder as well.
set -euo pipefail
family=${1:?usage: scripts/ship-model.sh chair|car [MAP_STEPS] [SPECULAR_STEPS]}
map_steps=${2:-4000}
specular_steps=${3:-1500}
bin=${NGP_MI:-.venv/bin/ngp-mi}
case "$family" in
  chair) constants=() ;;
  # the car family's R_BP constants (paper: k_d 0.6, k_s 0.4); R_diff at the albedo's own reflectance
  # (k_diff 1, as the chairs): at 0.6 NGP's diffuse image lacks 40 % of the car's light and G_sp^real
  # learns to paint it in (validation NGP FLIP 0.192 against 0.123 at 1; bench/RESULTS.md). The shipped
  # car: the map networks of SEED=1 at k_diff 0.6 (k_diff is in no network's weights), then its
  # G_sp^real stage re-trained with MAPS_FROM=car SEED=2 and these constants.
  car) constants=(--set model.k_d=0.6 --set model.k_diff=1.0 --set model.k_s=0.4 --set specular.lambda_sparse=10) ;;
  *) echo "ship-model: family must be chair or car, got '$family'" >&2; exit 2 ;;
esac
runs=outputs/train
held_out=outputs/data/held_out_$family
mkdir -p "$runs"

maps_threads=1
if [ -n "${SHAPE_FROM:-}" ]; then
  shape_args=(--shape-from "$SHAPE_FROM")
  maps_threads=$(nproc)
  true &  # nothing to train
else
  shape_args=(--shape-run "$runs/shape_$family")
  OMP_NUM_THREADS=1 "$bin" train shape --config train/shape_cpu.toml --out "$runs/shape_$family" \
    --set data.source="$family" --set data.cache_dir="outputs/data/shape_$family" &
fi
shape=$!
maps_run=$runs/maps_$family${MAPS_FROM:+_sp}
OMP_NUM_THREADS=$maps_threads "$bin" train maps --config train/maps_cpu.toml --out "$maps_run" \
  --set data.source="$family" --set data.cache_dir="outputs/data/maps_$family" \
  --set train.iterations="$map_steps" --set specular.iterations="$specular_steps" "${constants[@]}" \
  ${SEED:+--set train.seed="$SEED"} ${MAPS_FROM:+--maps-from "$MAPS_FROM"} &
maps=$!
wait "$shape"
wait "$maps"

# held-out shapes (seeds 500–519, 4 views, path-traced references) for the card's figures
"$bin" render-dataset --source "$family" --out "$held_out" --num-shapes 20 --views 4 --res 64 --seed 500 \
  --real-spp 64 --quiet
"$bin" evaluate maps --run "$maps_run" --data "$held_out" --coarse-sigma 2
"$bin" compare --source "$family" --out "$maps_run/compare" --num-shapes 10 --views 4 --res 64 \
  --seed 500 --lights rig --maps-checkpoint "$maps_run"
"$bin" export-model --maps-run "$maps_run" "${shape_args[@]}" \
  ${SPECULAR_FROM:+--specular-from "$SPECULAR_FROM"} --out "ngp_mi/pretrained/$family" --family "$family" \
  --notes "${SHAPE_FROM:+SHAPE_FROM=$SHAPE_FROM }${MAPS_FROM:+MAPS_FROM=$MAPS_FROM }${SPECULAR_FROM:+SPECULAR_FROM=$SPECULAR_FROM }${SEED:+SEED=$SEED }scripts/ship-model.sh $family $map_steps $specular_steps on $(nproc --all) CPU cores, $(date -u +%F)"
