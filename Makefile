# The two entry points a newcomer needs (see README):
#   make pipeline   set up .venv and run the DVC pipeline (paper profile on a GPU, ci profile otherwise)
#   make test       set up .venv and run the test suite (CPU; includes a CI-profile pipeline smoke run)
.PHONY: setup pipeline test
setup:
	bash scripts/setup.sh
pipeline: setup
	bash scripts/pipeline.sh
test: setup
	. .venv/bin/activate && HF_HUB_OFFLINE=1 DVC_NO_ANALYTICS=1 OMP_WAIT_POLICY=PASSIVE python -m pytest -m "not gpu" -q -n 2 --dist loadfile
