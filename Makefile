# The two fresh-machine commands of the README.
#   make main   set up, then run the Push-T main job (data -> train SDP -> lerobot-eval -> summary)
#   make test   set up, lint (ruff check + format check), then run the test suite (what CI runs)
#   make test-fast   the core tests only, for the edit loop
.PHONY: setup main robomimic lint test test-fast mutation

setup:
	bash .ci/setup

main: setup
	.venv/bin/lerobot-sdp-pusht $(ARGS)

# robomimic's main job: scripted Can demonstrations -> train SDP (CPU config) -> lerobot-eval -> summary
robomimic: setup
	.venv/bin/lerobot-sdp-robomimic $(ARGS)

lint: setup
	.venv/bin/ruff check . && .venv/bin/ruff format --check .

PYTEST = HF_HUB_OFFLINE=1 WANDB_MODE=disabled MUJOCO_GL=$${MUJOCO_GL:-egl} .venv/bin/python -m pytest -q
# pytest exits 5 when it collected no test: that must fail, not pass as green.
NO_TESTS_FAILS = rc=$$?; if [ $$rc -eq 5 ]; then echo "error: pytest collected no tests" >&2; exit 1; fi; exit $$rc

# The suite runs on TEST_JOBS pytest-xdist workers (TEST_JOBS=0: in this process), one torch thread
# each: two workers fill a 2-core CPU, and more threads than cores slow every test down.
TEST_JOBS ?= 2
test: setup lint
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-1} $(PYTEST) -n $(TEST_JOBS) $(PYTEST_ARGS); $(NO_TESTS_FAILS)

# The edit loop: the algorithm core, the policy and the package's layers, no end-to-end CLI run.
FAST_TESTS = tests/test_buffer*.py tests/test_geometry.py tests/test_schedule.py tests/test_noise_schemes.py \
	tests/test_streaming_step.py tests/test_modeling_sdp.py tests/test_configuration_sdp.py tests/test_layers.py
test-fast: setup
	$(PYTEST) -m "not slow" $(FAST_TESTS) $(PYTEST_ARGS); $(NO_TESTS_FAILS)

# Mutation check of the streaming core (buffer, schedule, geometry, noise schemes): every listed
# single-line bug must fail the core tests (about an hour on 2 CPU cores with ARGS="--jobs 2"; report in outputs/mutants/).
mutation: setup
	.venv/bin/python .ci/mutants.py $(ARGS)
