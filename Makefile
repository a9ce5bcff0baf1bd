# Convenience targets; each one is a single script a newcomer can also run directly.
.PHONY: test serve default-model

test:
	bash scripts/test.sh

serve:
	bash scripts/serve.sh

# Train, evaluate and install the shipped default model from scratch (CPU: hours; GPU: faster).
default-model:
	bash scripts/train_default.sh
