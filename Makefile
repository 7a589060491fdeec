# Every target creates/uses the local virtual environment .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

ENV   ?= point_u_maze
ALGO  ?= mb_dscpp
SEED  ?= 0
ARGS  ?=
RUN   ?=
SEEDS ?=
FIG   ?= all

.PHONY: install test train eval plot video reproduce bench-env bench-learners bench-options bench-seeds clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,tensorboard,wandb,video,warp]'
	touch $(STAMP)

install: $(STAMP)

# One process per test file: late in a single ~160-test process, XLA's CPU compiler has crashed
# (SIGSEGV while compiling a function that compiles fine in a fresh process).
# Compiling is most of the suite's time, so the files compile without XLA's expensive LLVM passes
# (about a fifth less in all), except test_trainer.py: its learning runs execute more than they
# compile, and it compares the interpreted MPC kernel with XLA's path at 1e-5.
FAST_XLA := --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true
test: $(STAMP)
	@fail=0; for f in tests/test_*.py; do echo "== $$f"; \
	  case $$f in tests/test_trainer.py) flags= ;; *) flags="$${XLA_FLAGS:+$$XLA_FLAGS }$(FAST_XLA)" ;; esac; \
	  env $${flags:+XLA_FLAGS="$$flags"} $(BIN)/python -m pytest -q -p no:cacheprovider $$f || fail=1; done; \
	  if [ $$fail = 0 ]; then echo "all test files passed"; else echo "some test files FAILED"; fi; \
	  exit $$fail

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
# table to experiments/results/paper. Re-run the same command to continue. See docs/training.md.
reproduce: $(STAMP)
	$(BIN)/python experiments/reproduce.py --fig $(FIG) $(ARGS)

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
