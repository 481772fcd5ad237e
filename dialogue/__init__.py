"""The dialogue process: the agent's ears and voice, one 80 ms step at a time.

Public API:
- `dialogue.process.create_component(cfg, run)`: the stage component (audio.user -> dialogue.step, transcript.json).
- `dialogue.backend.build_backend(cfg, seed)`: a backend with `spec`, `reset()`, `step(user_pcm) -> DialogueStep`,
  `transcript`; backends: `local` (VAD + pocketsphinx + responder + espeak-ng + speech tokenizer),
  `playback` (the agent speaks a recording), `moshi` (Kyutai's Moshi from local files).
- `dialogue.text_vocab.LOCAL_SPEC` / `word_token(word)`: the local backends' condition spec and text ids.
- `dialogue.speech_tokenizer.SpeechTokenizer.load(path)` / `StreamingSpeechEncoder`: 8 codes per step.
"""
