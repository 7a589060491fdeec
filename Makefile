# Every target creates/uses the local virtual environment .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

# GPU=1 installs JAX's CUDA wheels and MuJoCo Warp (the `cuda` extra); GPU=0 the CPU build. By
# default the GPU build is chosen where `nvidia-smi` lists a GPU.
GPU ?= $(shell nvidia-smi -L >/dev/null 2>&1 && echo 1 || echo 0)
EXTRAS := dev,tensorboard,wandb,video,$(if $(filter 1,$(GPU)),cuda,warp)

ENV   ?= point_u_maze
ALGO  ?= mb_dscpp
SEED  ?= 0
ARGS  ?=
RUN   ?=
SEEDS ?=
FIG   ?= all
THRESHOLD ?= 0.9
LIMIT ?= 600

.PHONY: install test train eval plot video reproduce time-to-result bench-env bench-learners bench-options bench-seeds clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[$(EXTRAS)]'
	echo '$(EXTRAS)' > $(STAMP)

# Re-install when the GPU choice changed since the last install (a CPU build on a GPU machine).
ifneq ($(wildcard $(STAMP)),)
ifneq ($(shell cat $(STAMP) 2>/dev/null),$(EXTRAS))
$(STAMP): FORCE
endif
endif
.PHONY: FORCE
FORCE:

install: $(STAMP)

# Each test file in its own process, two at a time on two cores (tests/run_files.py says why).
test: $(STAMP)
	$(BIN)/python tests/run_files.py $(ARGS)

train: $(STAMP)
	$(BIN)/python -m dscpp_jax.cli train --env $(ENV) --algo $(ALGO) $(if $(SEEDS),--seeds $(SEEDS),--seed $(SEED)) $(ARGS)

eval: $(STAMP)
	@test -n "$(RUN)" || (echo "usage: make eval RUN=runs/<run-dir> [ARGS=...]"; exit 2)
	$(BIN)/python -m dscpp_jax.cli eval --run $(RUN) $(ARGS)

plot: $(STAMP)
	@test -n "$(RUN)" || (echo "usage: make plot RUN='runs/<a> runs/<b>' [ARGS=...]"; exit 2)
	$(BIN)/python -m dscpp_jax.cli plot $(RUN) $(ARGS)

# MP4s of evaluation episodes in RUN/videos (top-down and following camera); MuJoCo renders
# through EGL or OSMesa, whichever loads (MUJOCO_GL=egl on a GPU host).
video: $(STAMP)
	@test -n "$(RUN)" || (echo "usage: make video RUN=runs/<run-dir> [ARGS='--episodes 2 --every 2']"; exit 2)
	$(BIN)/python -m dscpp_jax.cli video --run $(RUN) $(ARGS)

# The paper's figures (FIG=4|5|6|A1|A2|A3|all, comma lists too): trains the seed groups they need
# under runs/paper (skipping finished ones, resuming the others), writes PNG + CSV and a claims
# table to experiments/results/paper. Re-run the same command to continue. See docs/cli.md.
reproduce: $(STAMP)
	$(BIN)/python experiments/reproduce.py --fig $(FIG) $(ARGS)

# Time to result (ant mazes, in-band evaluation): the seeds of SEEDS (0-4 unless given) one after
# another, each stopped where its in-band success first reaches THRESHOLD or after LIMIT seconds;
# run directories, a summary table (summary_ENV-ALGO.md) and its figure (time_to_threshold_ENV-ALGO.png)
# under runs/time_to_result.
time-to-result: $(STAMP)
	$(BIN)/python experiments/time_to_threshold.py --dest runs/time_to_result --name $(ENV)-$(ALGO) \
	  --seeds $(or $(SEEDS),0-4) --threshold $(THRESHOLD) --limit $(LIMIT) -- --env $(ENV) --algo $(ALGO) $(ARGS)
	$(BIN)/python experiments/plot_time_to_threshold.py runs/time_to_result/summary_$(ENV)-$(ALGO).json \
	  --out runs/time_to_result/time_to_threshold_$(ENV)-$(ALGO).png

bench-env: $(STAMP)
	$(BIN)/python experiments/bench_env.py $(ARGS)

bench-learners: $(STAMP)
	$(BIN)/python experiments/bench_learners.py $(ARGS)

bench-options: $(STAMP)
	$(BIN)/python experiments/bench_options.py $(ARGS)

bench-seeds: $(STAMP)
	$(BIN)/python experiments/bench_seeds.py $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache
