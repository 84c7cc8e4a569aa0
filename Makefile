# The two fresh-machine commands of the README.
#   make main   set up, then run the Push-T main job (data -> train SDP -> lerobot-eval -> summary)
#   make test   set up, lint (ruff check + format check), then run the test suite (what CI runs)
.PHONY: setup main lint test mutation

setup:
	bash .ci/setup

main: setup
	.venv/bin/lerobot-sdp-pusht $(ARGS)

lint: setup
	.venv/bin/ruff check . && .venv/bin/ruff format --check .

# pytest exits 5 when it collected no test: that must fail CI, not pass as green.
test: setup lint
	HF_HUB_OFFLINE=1 WANDB_MODE=disabled MUJOCO_GL=$${MUJOCO_GL:-egl} .venv/bin/python -m pytest -q $(PYTEST_ARGS); \
	rc=$$?; if [ $$rc -eq 5 ]; then echo "error: pytest collected no tests" >&2; exit 1; fi; exit $$rc

# Mutation check of the streaming core (buffer, schedule, geometry, noise schemes): every listed
# single-line bug must fail the core tests (about 20 min on 2 CPU cores; report in outputs/mutants/).
mutation: setup
	.venv/bin/python .ci/mutants.py $(ARGS)
