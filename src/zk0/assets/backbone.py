"""A tiny SmolVLM-shaped backbone directory, built offline.

SmolVLA builds its vision-language backbone from ``vlm_model_name`` with
``AutoConfig``/``AutoProcessor``. With ``load_vlm_weights=False`` it needs only the
config, the tokenizer and the processor files, so a few-layer SmolVLM config plus a
BPE tokenizer trained here on robot-task text gives a real SmolVLA policy of well
under a million parameters that trains on a CPU in milliseconds per step. The real
backbone (``HuggingFaceTB/SmolVLM2-500M-Video-Instruct``) is the same code path.
"""

from __future__ import annotations

import json
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

IMAGE_SIZE = 64
PATCH_SIZE = 16
SCALE_FACTOR = 2
VOCAB_SIZE = 512

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


def _model_config(tokenizer: PreTrainedTokenizerFast) -> SmolVLMConfig:
    """A SmolVLM config with the real architecture and toy sizes."""
    head_dim = 16
    text_config = {
        "model_type": "llama",
        "vocab_size": len(tokenizer),
        "hidden_size": 64,
        "intermediate_size": 128,
        "num_hidden_layers": 2,
        "num_attention_heads": 4,
        "num_key_value_heads": 2,
        "head_dim": head_dim,
        "max_position_embeddings": 2048,
        "rope_theta": 100000.0,
        "rms_norm_eps": 1e-5,
        "pad_token_id": tokenizer.pad_token_id,
        "tie_word_embeddings": False,
    }
    vision_config = {
        "hidden_size": 32,
        "intermediate_size": 64,
        "num_hidden_layers": 1,
        "num_attention_heads": 2,
        "image_size": IMAGE_SIZE,
        "patch_size": PATCH_SIZE,
    }
    return SmolVLMConfig(
        text_config=text_config,
        vision_config=vision_config,
        scale_factor=SCALE_FACTOR,
        image_token_id=tokenizer.convert_tokens_to_ids("<image>"),
        pad_token_id=tokenizer.pad_token_id,
    )


def build_tiny_backbone(out_dir: Path) -> Path:
    """Write config, tokenizer and processor files for a tiny SmolVLM into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    tokenizer = _train_tokenizer()
    config = _model_config(tokenizer)
    image_processor = SmolVLMImageProcessor(
        do_image_splitting=False,
        size={"longest_edge": IMAGE_SIZE},
        max_image_size={"longest_edge": IMAGE_SIZE},
    )
    video_processor = SmolVLMVideoProcessor(
        size={"longest_edge": IMAGE_SIZE}, max_image_size={"longest_edge": IMAGE_SIZE}
    )
    image_seq_len = (IMAGE_SIZE // PATCH_SIZE) ** 2 // SCALE_FACTOR**2
    processor = SmolVLMProcessor(
        image_processor=image_processor,
        tokenizer=tokenizer,
        video_processor=video_processor,
        image_seq_len=image_seq_len,
        chat_template=CHAT_TEMPLATE,
    )
    config.save_pretrained(out_dir)
    processor.save_pretrained(out_dir)
    (out_dir / "zk0_backbone.json").write_text(
        json.dumps({"kind": "tiny-smolvlm", "image_size": IMAGE_SIZE, "vocab_size": len(tokenizer)})
    )
    return out_dir
