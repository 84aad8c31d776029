"""The vision-language-action model, its language encoder and the inference wrapper."""
