"""A tiny SmolVLM-shaped backbone directory, built offline.

SmolVLA builds its vision-language backbone from ``vlm_model_name`` with
``AutoConfig``/``AutoProcessor``. With ``load_vlm_weights=False`` it needs only the
config, the tokenizer and the processor files, so a few-layer SmolVLM config plus a
BPE tokenizer trained here on robot-task text gives a real SmolVLA policy of well
under a million parameters that trains on a CPU in milliseconds per step. The same
builder with SmolVLM2-500M's sizes gives a full-size SmolVLA with random weights for
benchmarks. The real backbone (``HuggingFaceTB/SmolVLM2-500M-Video-Instruct``) is the
same code path.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
from transformers import PreTrainedTokenizerFast, SmolVLMConfig, SmolVLMProcessor
from transformers.models.smolvlm.image_processing_smolvlm import SmolVLMImageProcessor
from transformers.models.smolvlm.video_processing_smolvlm import SmolVLMVideoProcessor

# The special tokens SmolVLM's processor and lerobot's SmolVLA look up by attribute.
EXTRA_SPECIAL_TOKENS = {
    "fake_image_token": "<fake_token_around_image>",
    "image_token": "<image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
}
BASE_SPECIAL_TOKENS = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<pad>", "<unk>"]

VOCAB_SIZE = 512  # the locally trained tokenizer's vocabulary


@dataclass(frozen=True)
class BackboneShape:
    """The sizes of a SmolVLM-shaped backbone; the architecture is always SmolVLM's."""

    text_hidden: int
    text_intermediate: int
    text_layers: int
    text_heads: int
    text_kv_heads: int
    head_dim: int
    vocab_size: int  # >= the tokenizer's; the real model's embedding size for full-size figures
    vision_hidden: int
    vision_intermediate: int
    vision_layers: int
    vision_heads: int
    image_size: int
    patch_size: int
    scale_factor: int


# Well under a million parameters as SmolVLA: trains on a CPU in milliseconds per step.
TINY = BackboneShape(64, 128, 2, 4, 2, 16, VOCAB_SIZE, 32, 64, 1, 2, 64, 16, 2)
# The tiny model with eyes for the simulator: 128 px cameras in 8 px patches give 64 visual tokens per
# camera (the tiny one's 64 px in 16 px patches give 4, where a 3 cm cube is about 3 pixels: a policy
# trained on it does not find the cube; docs/simulation.md has the measurements).
TINY_128 = BackboneShape(64, 128, 2, 4, 2, 16, VOCAB_SIZE, 64, 128, 1, 2, 128, 8, 2)
# SmolVLM2-500M-Video-Instruct's shape with random weights: realistic GPU figures without the Hub.
SMOLVLM2_500M = BackboneShape(960, 2560, 32, 15, 5, 64, 49280, 768, 3072, 12, 12, 512, 16, 4)


# A compact chat template: SmolVLA never renders chats, but AutoProcessor expects one.
CHAT_TEMPLATE = (
    "{% for message in messages %}{{ message['role'] | capitalize }}: "
    "{% for line in message['content'] %}{% if line['type'] == 'text' %}{{ line['text'] }}"
    "{% elif line['type'] == 'image' %}<image>{% endif %}{% endfor %}<end_of_utterance>\n"
    "{% endfor %}{% if add_generation_prompt %}Assistant:{% endif %}"
)

_CORPUS_WORDS = (
    "pick place the red green blue yellow orange purple white black cube block ball cup bowl "
    "box bin tray into onto on in left right front back top bottom center move grasp grab put "
    "stack sort push pull lift drop open close gripper arm robot so100 so101 shoulder elbow "
    "wrist pan roll flex joint camera front wrist laptop phone table target reach go to and a an "
    "of with near far small large first second pick up place it there 0 1 2 3 4 5 6 7 8 9"
)


def _corpus() -> list[str]:
    """Robot-task sentences; enough variety for a stable small BPE vocabulary."""
    words = _CORPUS_WORDS.split()
    lines = [" ".join(words[i : i + 8]) for i in range(0, len(words), 4)]
    return lines + [w.capitalize() for w in words] + [w.upper() for w in words]


def _train_tokenizer() -> PreTrainedTokenizerFast:
    """Train a byte-level BPE tokenizer offline and wrap it the way SmolVLM ships its own."""
    bpe = Tokenizer(models.BPE(unk_token="<unk>"))
    bpe.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    bpe.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=VOCAB_SIZE - len(EXTRA_SPECIAL_TOKENS),
        special_tokens=BASE_SPECIAL_TOKENS,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    bpe.train_from_iterator(_corpus(), trainer=trainer)
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=bpe,
        bos_token="<|im_start|>",
        eos_token="<end_of_utterance>",
        pad_token="<pad>",
        unk_token="<unk>",
        extra_special_tokens=EXTRA_SPECIAL_TOKENS,
        model_max_length=2048,
    )
    tokenizer.add_special_tokens({"additional_special_tokens": list(EXTRA_SPECIAL_TOKENS.values())})
    return tokenizer


def _model_config(tokenizer: PreTrainedTokenizerFast, shape: BackboneShape) -> SmolVLMConfig:
    """A SmolVLM config with the real architecture and ``shape``'s sizes."""
    text_config = {
        "model_type": "llama",
        "vocab_size": max(shape.vocab_size, len(tokenizer)),
        "hidden_size": shape.text_hidden,
        "intermediate_size": shape.text_intermediate,
        "num_hidden_layers": shape.text_layers,
        "num_attention_heads": shape.text_heads,
        "num_key_value_heads": shape.text_kv_heads,
        "head_dim": shape.head_dim,
        "max_position_embeddings": 2048,
        "rope_theta": 100000.0,
        "rms_norm_eps": 1e-5,
        "pad_token_id": tokenizer.pad_token_id,
        "tie_word_embeddings": False,
    }
    vision_config = {
        "hidden_size": shape.vision_hidden,
        "intermediate_size": shape.vision_intermediate,
        "num_hidden_layers": shape.vision_layers,
        "num_attention_heads": shape.vision_heads,
        "image_size": shape.image_size,
        "patch_size": shape.patch_size,
    }
    return SmolVLMConfig(
        text_config=text_config,
        vision_config=vision_config,
        scale_factor=shape.scale_factor,
        image_token_id=tokenizer.convert_tokens_to_ids("<image>"),
        pad_token_id=tokenizer.pad_token_id,
    )


def build_backbone(out_dir: Path, shape: BackboneShape) -> Path:
    """Write config, tokenizer and processor files for a SmolVLM of ``shape`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    tokenizer = _train_tokenizer()
    config = _model_config(tokenizer, shape)
    edge = {"longest_edge": shape.image_size}
    image_processor = SmolVLMImageProcessor(do_image_splitting=False, size=edge, max_image_size=edge)
    video_processor = SmolVLMVideoProcessor(size=edge, max_image_size=edge)
    image_seq_len = (shape.image_size // shape.patch_size) ** 2 // shape.scale_factor**2
    processor = SmolVLMProcessor(
        image_processor=image_processor,
        tokenizer=tokenizer,
        video_processor=video_processor,
        image_seq_len=image_seq_len,
        chat_template=CHAT_TEMPLATE,
    )
    config.save_pretrained(out_dir)
    processor.save_pretrained(out_dir)
    return out_dir
