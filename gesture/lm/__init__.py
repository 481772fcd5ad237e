"""The gesture language model: its options (`config`), the training model (`model`, `layers`, `embeddings`), its
training (`train`, `data`, `losses`, `schedule`, `tokenize`), and the fast step path (`stepper` on
`step_weights`; `naive` is the tests' oracle)."""
