# Set-up is part of every target: a fresh clone needs nothing but Python 3.11+.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test fuzz bench bench-anytime bench-systems bench-external bench-derived bench-iterations bench-limits bench-startup bench-tracking bench-dynobench bench-ablation lint clean-venv

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,dask,ompl,direct,mlp,dynobench]"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/rrtcolearn run

test: $(STAMP)
	$(BIN)/python -m pytest

# the property-based tests on hypothesis's random "wide" profile (5 000 examples each, ten times
# the derandomized "ci" profile `make test` runs, a new draw every run), then 100 000 seeded
# random damages each of a dataset, a model and a plan file (bench/damage_fuzz.py: about
# 1, 5 and 0.5 CPU minutes)
fuzz: $(STAMP)
	HYPOTHESIS_PROFILE=wide $(BIN)/python -m pytest tests/test_fuzz.py
	for a in dataset model plan; do \
	    $(BIN)/python bench/damage_fuzz.py --artefact $$a --trials 100000 || exit 1; done

bench: $(STAMP)
	$(BIN)/python bench/run_bench.py

# the per-system figures in full (50 seeded swing-ups of at most 60 s each): about 30 minutes
bench-systems: $(STAMP)
	$(BIN)/python bench/systems_bench.py

# sparse_rrt's cart-pole and acrobot (examples/) with every setting derived, 20 seeds of at
# most 60 s each, with the ratio to sparse_rrt's SST: about 40 minutes per problem
bench-external: $(STAMP)
	$(BIN)/python bench/systems_bench.py --queries 20 --systems \
	    examples.sparse_rrt_cartpole:make_cartpole,examples.sparse_rrt_acrobot:make_acrobot

# the pendulum with derived settings beside the paper's, side by side (about 3 minutes)
bench-derived: $(STAMP)
	$(BIN)/python bench/derived_ab.py

# two anytime schemes (restarts, restarts + goal shortcuts) at equal CPU on the pendulum against
# the collocation optimum and OMPL RRT's first solution (1-4 minutes: 1 min 6 s on an idle machine)
bench-anytime: $(STAMP)
	$(BIN)/python bench/anytime.py

# planner iteration cost at 100, 1 000 and 10 000 tree nodes (about a minute)
bench-iterations: $(STAMP)
	$(BIN)/python bench/iteration_cost.py

# the input-limit table with its comparison row (w = 10 at the paper's cost bound): about 11 minutes
bench-limits: $(STAMP)
	$(BIN)/python bench/limits_bench.py

# one `rrtcolearn plan` and `--help` in fresh processes, first against warm planning CPU
# (about a minute; makes runs/pendulum-swingup first if it holds no model)
# STARTUP_SYSTEMS="runs/acrobot runs/cartpole": also one plan call of each of these runs
bench-startup: $(STAMP)
	$(BIN)/python bench/startup.py $(if $(STARTUP_SYSTEMS),--systems $(STARTUP_SYSTEMS))

# plans tracked by time-varying LQR against open-loop on systems 10% heavier, with noise and a
# start error, 100 runs each (makes the five plans into runs/tracking first if missing)
bench-tracking: $(STAMP)
	$(BIN)/python bench/tracking_bench.py

# dynobench's unicycle problems against its reference solutions, exact bodies against inflation,
# and the collision test's cost per RK4 step (docs/dynobench.md; shapely for the library row)
bench-dynobench: $(STAMP)
	$(BIN)/python -m pip install --quiet shapely
	$(BIN)/python bench/dynobench_bench.py

# issue 31's ablation: learned steering only / random controls only / the default on nine
# problems against their optima (docs/ablation.md). This default (5 seeds of at most 20 CPU
# s, 2 anytime seeds of 10 CPU s, small k-NN models fitted once into /tmp) takes about 13
# CPU minutes; the issue's full table: ABLATION_ARGS="--seeds 20 --anytime-seeds 20 --limit 60"
ABLATION_ARGS ?= --seeds 5 --anytime-seeds 2 --limit 20 --anytime 10
bench-ablation: $(STAMP)
	$(BIN)/python bench/ablation.py $(ABLATION_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check src tests bench

clean-venv:
	rm -rf $(VENV)
