"""The campaign config: one pydantic model, used by the CLI and as the Prefect flow parameter.

Every model forbids unknown keys, so a typo is refused with its field named, before any work.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schemas.errors import Sim2ActError
from schemas.keys import key_fields
from schemas.tasks import FAMILIES, Colour, Family

CameraName = Literal["agentview", "frontview", "birdview", "sideview"]
PRESETS = ("smoke", "default", "headline", "curriculum", "hard-mix", "generalist")

PositiveInt = Annotated[int, Field(gt=0)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ChatEndpointConfig(_Strict):
    """An OpenAI-compatible chat-completions endpoint (Ollama, vLLM, llama.cpp server, a hosted API)."""

    url: str = Field(pattern=r"^https?://", description="base URL, e.g. http://127.0.0.1:11434/v1")
    model: str = Field(min_length=1, description="the model name the endpoint serves, as its API takes it")
    timeout_s: float = Field(default=60.0, gt=0, description="per request")
    retries: int = Field(default=2, ge=0, description="further tries after a timeout, refused connection or 5xx")
    temperature: float = Field(default=0.7, ge=0.0, le=2.0, description="sampling temperature of the answers")
    api_key_env: str | None = Field(default=None, description="environment variable holding the API key")


class ProposerConfig(ChatEndpointConfig):
    """A chat endpoint that proposes tasks."""

    proposals: PositiveInt = Field(default=10, description="tasks asked for in the one request (a proposal of an "
                                   "existing task adds paraphrases to it)")
    fallback_to_templates: bool = Field(default=False, description="if unreachable: templates only, not failure")


class VlmExplorerConfig(ChatEndpointConfig):
    """A multimodal chat endpoint that explores: one request per step, the frame and the instruction in,
    a JSON action out (policies/vlm_explorer.py, docs/explorers.md)."""

    # A step waits on the request, so a slow or absent server must fail fast, not stall a worker.
    timeout_s: float = Field(default=10.0, gt=0, description="per request")
    retries: int = Field(default=1, ge=0, description="further tries after a timeout, refused connection or 5xx")
    temperature: float = Field(default=0.0, ge=0.0, le=2.0, description="0: the most likely action")
    max_tokens: PositiveInt = Field(default=64, description="the answer is one short JSON object")
    max_invalid_answers: int = Field(
        default=10, ge=0, description="invalid answers an episode absorbs as no-ops; one more fails the episode"
    )


class TasksConfig(_Strict):
    """Which task specs (schemas/task_specs/*.yaml, plus the user's spec_files) a campaign uses."""

    specs: list[str] = Field(default=["lift", "stack"], min_length=1, description="spec names")
    spec_files: list[Path] = Field(default=[], description="extra YAML spec files")
    colours: list[Colour] | None = Field(default=None, description="bind only these colours (default: the spec's)")
    unseen_colours: list[Colour] = Field(default=[], description="held out in addition to each spec's own")
    max_tasks_per_spec: PositiveInt | None = Field(
        default=None, description="bind at most this many colourings of each spec, in the spec's order (after "
        "the tasks left out for a weak expert); None: every one")
    paraphrases: int = Field(default=3, ge=3, description="instructions per task, canonical included")
    include: list[str] | None = Field(default=None, description="keep only these task ids")
    horizon: dict[str, PositiveInt] = Field(default={}, description=(
        "per-spec horizon override (one shorter than the spec's mean expert episode, docs/experts.md, is said in "
        "one line: few of its episodes can succeed)"))
    proposer: ProposerConfig | None = Field(default=None, description="optional LLM task proposer")
    weak_experts: Literal["skip", "keep"] = Field(
        default="skip", description="tasks whose scripted expert is below 90% (docs/experts.md; and under the campaign's "
        "randomisation where an expert feels it: masses, sizes, frictions, measured once per workspace): skip or keep"
    )

    @model_validator(mode="after")
    def _specs_once(self) -> TasksConfig:
        repeated = sorted({name for name in self.specs if self.specs.count(name) > 1})
        if repeated:  # each would bind the same tasks twice
            raise ValueError(f"specs: expected each spec once, got {repeated[0]!r} {self.specs.count(repeated[0])} times")
        return self


class RenderConfig(_Strict):
    """How frames are rendered; recorded per campaign so training and evaluation see alike."""

    camera: CameraName = Field(default="agentview", description="the view a policy sees (robosuite's camera "
                               "names; MetaWorld and navigation map each to a camera of their own scene)")
    image_size: int = Field(default=84, ge=32, le=256, description="side of each view's square frame, in pixels")
    # Shadows, reflections and multisampling cost 3-4x render time on CPU (docs/rollouts.md: 4x MSAA
    # alone took raw rendering from 48 to 27 frames/s) and add little a policy needs at 84 px.
    shadows: bool = Field(default=False, description="draw shadows (MuJoCo's shadow maps)")
    reflections: bool = Field(default=False, description="draw reflective surfaces")
    multisamples: int = Field(default=0, ge=0, le=16, description="anti-aliasing samples per pixel (MSAA); 0: off")
    depth: bool = Field(default=False, description="also record a depth map with every frame; the policy then sees RGB-D")
    # Triangles are a CPU frame's cost (robosuite's visual meshes: 167k faces for Lift). Below 1, robosuite and
    # MetaWorld scenes draw each visual-only mesh decimated to this fraction of its faces (envs/mesh_detail.py):
    # physics unchanged, pixels not, so a campaign keeps one value (docs/rollouts.md has the speed-up).
    mesh_detail: float = Field(default=1.0, gt=0, le=1,
                               description="fraction of visual mesh faces drawn (robosuite, MetaWorld)")
    # A mesh that collides stays whole for physics, and was drawn whole too: MetaWorld's gripper base and last link
    # are 16k of the 23k faces its frame still draws at 0.1. Off by default: on, the frames differ from a campaign
    # that explored without it (a few edge pixels), so a campaign keeps one value.
    decimate_colliding: bool = Field(default=False, description="with mesh_detail below 1, also draw the meshes "
                                     "that collide decimated (the renderer's copy only: physics keeps the full mesh)")
    # Precise placing (a nut on its peg) is a few pixels at 84 px from the agent's view; robomimic's and Diffusion
    # Policy's image figures for Square and Can see a second camera in the hand. Stored beside the main view in one
    # frame (H x 2H, schemas/frames.py), read by an encoder of its own (policies/model.py).
    wrist_camera: bool = Field(default=False, description="robosuite only: also render the hand's camera "
                               "(robot0_eye_in_hand) at image_size, right of the main view; the model reads both")

    @model_validator(mode="after")
    def _one_depth_view(self) -> RenderConfig:
        if self.wrist_camera and self.depth:
            raise ValueError("wrist_camera: depth maps are recorded for one view only, so not with render.depth")
        if self.decimate_colliding and self.mesh_detail >= 1.0:
            raise ValueError(f"decimate_colliding: expected render.mesh_detail below 1, got {self.mesh_detail}")
        return self

    @property
    def views(self) -> int:
        """Camera views side by side in every frame."""
        return 2 if self.wrist_camera else 1


# render fields added after the stages that key on the render settings: at these values a key reads as before
RENDER_LEGACY_VALUES = {"mesh_detail": 1.0, "wrist_camera": False, "decimate_colliding": False}


def recorded_render(episode_render: dict, unit_summary: dict) -> dict[str, Any]:
    """An episode's render settings as stored: `episodes.render` (a shard schema older than the fields added
    since) with those fields from its explore unit's summary, which keeps them where not at their legacy values."""
    return {**episode_render, **{field: unit_summary.get(field, legacy) for field, legacy in RENDER_LEGACY_VALUES.items()}}


def render_key_fields(render: RenderConfig) -> dict[str, Any]:
    """The render settings as explore, evaluate and baselines units key them (fields added later at
    their legacy value left out, so earlier work keeps its keys)."""
    return key_fields(render, set(), RENDER_LEGACY_VALUES)


Scale = tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]]


class RandomiseConfig(_Strict):
    """Domain randomisation, drawn per episode from its seed and recorded with the episode.

    Scales multiply the simulator's own value; each adapter applies the parts that mean
    something for it (a navigation ball has no mass that matters) and records the others as null.
    """

    enabled: bool = Field(default=True, description="draw every episode's light, camera, colours and object "
                          "physics from the ranges below by its seed; false: the simulator's nominal values "
                          "(placements still follow the seed)")
    light: Scale = Field(default=(0.6, 1.4), description="diffuse light intensity scale")
    camera_shift_m: float = Field(default=0.02, ge=0, le=0.2, description="max camera offset per axis, metres")
    camera_rotation_deg: float = Field(default=2.0, ge=0, le=15, description="max camera rotation per axis")
    tint: float = Field(default=0.15, ge=0, lt=1, description="max per-channel scale change of scene colours")
    # a campaign's cap is COLOUR_JITTER_MAX (CampaignConfig checks it); this bound is what stored records hold
    colour_jitter: float = Field(default=0.05, ge=0, le=0.2, description="max RGB offset of task object colours")
    size: Scale = Field(default=(0.9, 1.1), description="object size scale")
    mass: Scale = Field(default=(0.75, 1.25), description="object mass scale")
    friction: Scale = Field(default=(0.75, 1.25), description="object sliding friction scale (a contact takes its two "
                            "geoms' larger: below 1, an object of friction 1 keeps the table's and fingers')")

    @model_validator(mode="after")
    def _ranges_ordered(self) -> RandomiseConfig:
        for name in ("light", "size", "mass", "friction"):
            low, high = getattr(self, name)
            if low > high:
                raise ValueError(f"{name}: low {low} is above high {high}")
        return self


NoiseLevel = Annotated[float, Field(ge=0.0, le=1.0)]
Share = Annotated[float, Field(ge=0.0, le=1.0)]


def _levels(value: float | list[float]) -> list[float]:
    """A schedule's levels: a list as it is, one level as a list of one."""
    return value if isinstance(value, list) else [value]


class ExploreConfig(_Strict):
    episodes_per_task: PositiveInt = Field(default=8, description="episodes explored per seen task each iteration "
                                           "(iteration >= 1 shares them by priority: explore.prioritise)")
    first_episodes_per_task: PositiveInt | None = Field(
        default=None, description="iteration 0's episodes per seen task (the experts' seed set: MimicGen starts "
        "from 10), when the later iterations' budget is another (explore.episodes_per_task); None: the same"
    )
    episodes_per_shard: PositiveInt = Field(default=4, description="episodes of one task per explore unit (its "
                                            "episodes and steps shards): a kill loses at most the units in flight, "
                                            "one per worker")
    expert_noise: NoiseLevel | list[NoiseLevel] = Field(
        default=0.1, description="std of the expert's Gaussian action noise; a list is a schedule of levels cycled "
        "over each task's expert episodes (clean and noisy demonstrations side by side)"
    )
    policy_fraction: float = Field(
        default=0.5, ge=0.0, le=1.0, description="share of episodes the redeployed policy explores (iteration >= 1)"
    )
    prioritise: bool = Field(
        default=True, description="iteration >= 1: share the episode budget among the seen tasks by the champion's "
        "evaluation, low success and high uncertainty first (warehouse/priority.py)"
    )
    priority_floor: float = Field(
        default=0.25, ge=0.0, le=1.0, description="each task keeps at least this share of episodes_per_task"
    )
    vlm: VlmExplorerConfig | None = Field(default=None, description="a multimodal chat endpoint that explores too")
    vlm_fraction: float = Field(
        default=0.5, ge=0.0, le=1.0, description="share of the episodes the policy leaves that the VLM explores"
    )
    expert_labels: bool = Field(
        default=True, description="record the noiseless expert action at every state (DAgger labels)"
    )
    expert_takeover: Share | list[Share] = Field(
        default=0.0, description="DAgger's beta: in the policy's episodes, the share of steps on which "
        "the noiseless expert's action is executed instead of the policy's (drawn per step from the episode's seed; "
        "its labels recorded at every step as always), so the labelled states reach the phases a weak policy never "
        "gets to alone (a grasp, a carry); explorer_stats counts the steps it drove. A list is a schedule over "
        "iterations 1, 2, ... (the last level repeats), e.g. [0.5, 0.25, 0.125]: DAgger's beta_i falling as the "
        "policy's own states become the ones it must learn to recover from"
    )
    policy_steps: PositiveInt | None = Field(
        default=None, description="the policy's episodes (not the chained ones of explore.curriculum) end after "
        "this many steps, or at the task's horizon if sooner; None: the horizon. A model that has not learnt to "
        "find the object parts from the expert at its first steps (`sim2act shadow` placement table), so short "
        "episodes spend the steps on more placements, each one's first states labelled by the expert "
        "(explore.expert_labels), instead of on the late steps of a few. The filter judges a cut episode by its "
        "return like any other (filter.min_return)"
    )
    curriculum: bool = Field(
        default=False, description="long-horizon tasks (specs with subtasks) are learnt from their sub-tasks: no "
        "scripted expert explores or labels them; from iteration 1 the champion explores them by following each "
        "sub-task's instruction in turn (the environment says which goal is next), recorded under the task's own "
        "instruction; iteration 0 leaves them out"
    )
    relabel: bool = Field(
        default=False, description="hindsight relabelling (SOAR): a failed episode that ended satisfying another "
        "seen task of its environment (the navigation agent in another room, at another ball or box) is recorded "
        "as a success of that task, said with its words, its actions as executed (the expert's labels pointed "
        "at the first goal: dropped); explorer_stats names the task it set out to do",
    )
    workers: PositiveInt = Field(default=2, description="local worker processes (one core each)")
    dask_address: str | None = Field(
        default=None, pattern=r"^(tcp|tls|inproc|ucx)://", description="run shards on this Dask scheduler instead"
    )

    @model_validator(mode="after")
    def _schedule_not_empty(self) -> ExploreConfig:
        if self.expert_noise == []:
            raise ValueError("expert_noise: the schedule is empty; give one level or several")
        if self.expert_takeover == []:
            raise ValueError("expert_takeover: the schedule is empty; give one share or one per iteration")
        if max(_levels(self.expert_takeover)) > 0 and not self.expert_labels:
            raise ValueError(f"expert_takeover: expected expert_labels true (the expert that takes over is the one "
                             f"that labels), got expert_takeover {self.expert_takeover} with expert_labels false")
        return self

    def takeover_of(self, iteration: int) -> float:
        """The expert's share of the policy's steps at `iteration`: a schedule's level for it (the
        last one repeating). Iteration 0 has no policy to take over from; it reads the first level, as
        a single share reads the same at every iteration, so its explore key changes only with that."""
        levels = _levels(self.expert_takeover)
        return levels[min(max(iteration, 1), len(levels)) - 1]

    def episodes_at(self, iteration: int) -> int:
        """A seen task's episodes at `iteration` before any prioritising: first_episodes_per_task at 0."""
        return (self.first_episodes_per_task or self.episodes_per_task) if iteration == 0 else self.episodes_per_task

    def noise_of(self, expert_episode: int) -> float:
        """The noise level of a task's `expert_episode`-th expert episode."""
        levels = _levels(self.expert_noise)
        return levels[expert_episode % len(levels)]


class FilterConfig(_Strict):
    min_return: float = Field(default=0.0, description="episodes whose return is below this are rejected")
    require_success: bool = Field(default=False, description="keep only the episodes that reached their goal")


# What a model field added after the first checkpoints did before it existed: a checkpoint whose
# model_config lacks one loads with this value (not today's default), and a training at this value
# keeps the unit key it had before the field (stages/train.py LEGACY_VALUES).
MODEL_LEGACY_VALUES = {"chunk": 1, "execution": "temporal_ensemble", "execute_steps": None, "ensemble_decay": 0.01}


class ModelConfig(_Strict):
    """The VLA model's sizes (policies/model.py, docs/training.md)."""

    vision: Literal["vit", "hybrid", "resnet18"] = Field(
        default="hybrid",
        description="vision encoder, trained from scratch: a ViT over pixel patches; a ViT-hybrid over a ResNet-18 "
        "trunk's feature-map cells; or the ResNet-18 alone (its cells go straight to the fusion transformer)",
    )
    patch_size: PositiveInt = Field(default=12, description="ViT patch side in pixels; divides render.image_size")
    resnet_width: PositiveInt = Field(default=16, description="ResNet-18 channels of its first stage (64 in the paper)")
    keypoints: int = Field(
        default=32, ge=0, le=128,
        description="spatial-softmax keypoints (Levine et al. 2016) over the ResNet-18 trunk's stride-8 feature "
        "map, as one more vision token (hybrid, resnet18): where things are, finer than the trunk's 32 px cells; 0: none",
    )
    dim: PositiveInt = Field(default=64, description="width of every token and embedding (vision, fusion, the "
                             "contrastive space)")
    vision_depth: PositiveInt = Field(default=2, description="transformer layers of the vision encoder (vit, hybrid)")
    fusion_depth: PositiveInt = Field(default=2, description="transformer layers over the vision, language and "
                                      "proprioception tokens together")
    heads: PositiveInt = Field(default=4, description="attention heads per layer; divides dim")
    language_encoder: Literal["all-MiniLM-L6-v2"] = Field(
        default="all-MiniLM-L6-v2", description="the sentence encoder of the instructions (the packaged weights)")
    language_trainable: bool = Field(
        default=False, description="fine-tune the language encoder (else frozen: cached embeddings)"
    )
    chunk: int = Field(
        default=8, ge=1, le=64,
        description="actions predicted per observation, this step's and the next chunk-1 of its episode (ACT, "
        "Diffusion Policy: against compounding error); the InfoNCE action embedding reads the whole chunk; 1: one. "
        "8 by default: on the quality recipe chunk 8 reached 93-98% seen over three seeds where chunk 1's three "
        "landed in 25-88% (docs/training.md)",
    )
    execution: Literal["temporal_ensemble", "receding"] = Field(
        default="temporal_ensemble",
        description="how a chunked policy acts: temporal_ensemble predicts every step and averages every earlier "
        "chunk's prediction for this step, weights exp(-ensemble_decay * i), i = 0 the oldest (ACT); receding "
        "executes the first execute_steps actions of a chunk, then predicts again (Diffusion Policy)",
    )
    execute_steps: int | None = Field(
        default=None, ge=1, le=64, description="receding: actions executed per prediction; None: half the chunk"
    )
    ensemble_decay: float = Field(default=0.01, ge=0.0, description="temporal_ensemble: m in exp(-m i) (ACT: 0.01)")

    @model_validator(mode="after")
    def _heads_divide_dim(self) -> ModelConfig:
        if self.dim % self.heads:
            raise ValueError(f"dim {self.dim} is not divisible by heads {self.heads}")
        if self.execute_steps is not None and self.execute_steps > self.chunk:
            raise ValueError(f"execute_steps: expected at most chunk ({self.chunk}), got {self.execute_steps}")
        return self

    @property
    def steps_per_prediction(self) -> int:
        """receding: actions executed per prediction."""
        return self.execute_steps or max(1, self.chunk // 2)


class Acting(_Strict):
    """How a chunked policy turns its predictions into actions, chosen when it acts rather than when
    it trained (`sim2act shadow --execution`): the model predicts the same chunks either way, so one
    checkpoint can be measured under each; a field left None keeps the checkpoint's own."""

    execution: Literal["temporal_ensemble", "receding"] | None = None  # ModelConfig.execution
    execute_steps: int | None = Field(default=None, ge=1, le=64)  # receding: actions executed per prediction
    ensemble_decay: float | None = Field(default=None, ge=0.0)  # temporal_ensemble: m in exp(-m i)

    def applied_to(self, model: ModelConfig) -> ModelConfig:
        """`model` acting this way. Raises ValueError where the two do not fit (execute_steps > chunk)."""
        return ModelConfig(**{**model.model_dump(), **self.model_dump(exclude_none=True)})

    def describe(self) -> str:
        return ", ".join(f"{name} {value}" for name, value in self.model_dump(exclude_none=True).items())


class TrainConfig(_Strict):
    seed: int = Field(
        default=0, ge=0, description="training seed (weights, data order, augmentation) on the same dataset: "
        "the results protocol trains seeds 0..N-1 of one dataset (docs/evaluation.md)",
    )
    ema: float | None = Field(
        default=0.999, gt=0.0, lt=1.0,
        description="decay of an exponential moving average of the weights, warmed up as min(ema, (1+t)/(10+t)) at "
        "step t; the average is what gets evaluated, registered and explores (the last weights are kept beside "
        "it in the checkpoint); None: the last weights",
    )
    epochs: PositiveInt = Field(default=10, description="passes over the iteration's dataset (unless train.steps)")
    steps: PositiveInt | None = Field(
        default=None, description="optimiser steps per model instead of epochs: the epochs become ceil(steps / "
        "batches per epoch), so a training costs the same as the dataset grows over iterations; None: train.epochs",
    )
    batch_size: PositiveInt = Field(default=64, description="triplets per optimiser step")
    lr: float = Field(default=3e-4, gt=0, description="AdamW's peak learning rate")
    language_lr: float = Field(default=2e-5, gt=0, description="learning rate of a fine-tuned language encoder")
    weight_decay: float = Field(default=0.01, ge=0, description="AdamW's decoupled weight decay")
    contrastive_weight: float = Field(default=0.2, ge=0.0, le=1.0, description="lambda in lambda*InfoNCE + (1-lambda)*BC")
    temperature: float = Field(default=0.1, gt=0, description="InfoNCE's temperature (the contrastive term)")
    grad_clip: float = Field(default=1.0, gt=0, description="the gradients' global norm is clipped to this")
    shuffle_buffer: PositiveInt = Field(default=2048, description="triplets each loader worker's streaming reader "
                                        "shuffles among (more: batches less correlated, more memory)")
    augment_shift: int = Field(
        default=4, ge=0, le=16,
        description="shift each training frame by up to this many pixels each way (edges repeated); 0: off",
    )
    state_weight: float = Field(
        default=1.0, ge=0.0,
        description="weight of an auxiliary loss: a head on z_ol predicts the simulator state before the action (the "
        "steps' qpos, normalised per component), supervision available in simulation at training time only and read "
        "nowhere when acting; it asks the encoder where the objects are; 0: off (the recipe before session 13)",
    )
    proprio_dropout: float = Field(
        default=0.0, ge=0.0, le=1.0,
        description="share of training samples whose proprio is replaced by the dataset's mean (zero once "
        "normalised): the robot's start noise makes each episode's proprio unique, so a policy of few episodes can "
        "tell them apart by it and learn their first moves by heart instead of reading where the object is in the "
        "frame (causal confusion: de Haan et al. 2019, Wen et al. 2020); acting always reads proprio; 0: off",
    )
    targets: Literal["expert", "executed"] = Field(
        default="expert",
        description="what the policy learns to output: the expert's noiseless action at each state where the "
        "episode recorded one (expert explorers, DAgger labels), else the executed action; or always the "
        "executed action (exploration noise included)",
    )
    language_augment: float = Field(
        default=0.0, ge=0.0, le=1.0,
        description="share of training samples whose instruction is replaced by a rewording (other colour words, "
        "verbs, sentence shapes: schemas/wordings.py TRAINING_LEXICON, disjoint from the held-out wordings "
        "evaluation uses); 0: the generator's wordings only",
    )
    where: str | None = Field(
        default=None, min_length=1,
        description="SQL condition over the steps columns narrowing the iteration's kept steps, e.g. "
        "\"task_id LIKE 'lift-%'\"",
    )
    init_from: str | None = Field(
        default=None, min_length=1,
        description="fine-tune: the model key (in this workspace) whose weights and action/proprio statistics "
        "start the training; None: from scratch",
    )
    loader_workers: int = Field(
        default=1, ge=0, le=32, description="processes reading and decoding batches (0: the training process)"
    )
    ensemble: int = Field(
        default=1, ge=1, le=16, description="models trained alike, each from its own seed, whose mean actions the "
        "policy takes (their disagreement joins its uncertainty); each costs a training"
    )
    checkpoint_every: PositiveInt = Field(default=200, description="steps between resumable checkpoints")
    log_every: PositiveInt = Field(default=20, description="steps between MLflow metric points")
    device: Literal["auto", "cpu", "cuda"] = Field(default="auto", description="auto: cuda when there is one")
    amp: bool = Field(default=True, description="bf16 autocast where the device has bf16 matrix units: cuda, and "
                      "CPUs with AMX; with AVX-512 BF16 alone (0.94x-1.33x fp32 by core and batch) a long training "
                      "measures its own step both ways once and takes bf16 at >= 1.10x; emulated bf16 (8-16x slower) "
                      "never; policies/precision.py. The same rule puts the RL baselines' encoders in bf16 "
                      "during their updates (policies/rl_encoder.py)")
    threads: PositiveInt = Field(default=2, description=(
        "torch threads of the training step; beside other busy processes set 1: two threads on shared cores wait "
        "on each other at every parallel region (measured 35 samples/s at 2 against ~530 at 1 beside two busy SAC "
        "workers on 2 cores, docs/training.md)"))
    model: ModelConfig = ModelConfig()


class EvaluateConfig(_Strict):
    episodes_per_task: PositiveInt = Field(default=3, description="episodes per evaluation case (a task in one "
                                           "wording), each on its own seed")
    episodes_per_split: PositiveInt | None = Field(
        default=None, description="at least this many episodes in each split's cell: a split of n cases gets "
        "max(episodes_per_task, ceil(episodes_per_split / n)) per case (45 bounds a Wilson 95% interval to about "
        "+-15 points at any rate); None: episodes_per_task for every case",
    )
    held_out_wordings: bool = Field(
        default=False, description="also evaluate every seen task said in words the generator never uses "
        "(split held_out_wording: schemas/wordings.py), on the canonical wording's seeds")
    workers: PositiveInt = Field(default=2, description="processes evaluating cases at once")
    videos: bool = Field(default=True, description="an MP4 of the first success and the first failure per case")
    metaworld_placements: Literal["benchmark", "fresh"] = Field(
        default="benchmark", description="MetaWorld's object and goal placements in evaluation episodes: 'benchmark' "
        "takes MT1's 50 fixed ones per task (seed % 50, as exploration does: an evaluation episode mostly starts where "
        "an explored one did); 'fresh' draws each from the task's own reset space by the episode's seed (as "
        "robosuite and navigation always do), placements no exploration saw. `sim2act eval` names it in the suite")
    max_steps: PositiveInt | None = Field(
        default=None, description="end every evaluation episode after at most this many steps (a success within "
        "them still counts): a quick look, or a test's, whose success rates do not compare with full horizons, so "
        "its units are its own and `sim2act eval` names it in the suite; None: each task's horizon")
    training_seeds: PositiveInt = Field(
        default=1, le=16, description="trainings of each iteration's dataset (train.seed, train.seed + 1, ...): the "
        "first is the campaign's model (it competes for champion and explores the next iteration); the others, "
        "trained alike but for the seed, meet the same cases beside it, so every iteration's success comes with its "
        "spread across seeds (the results protocol asks 3: docs/evaluation.md); each costs a training and an evaluation",
    )

    def episodes_per_case(self, cases_in_split: int) -> int:
        """Episodes for each case of a split of `cases_in_split` cases."""
        if self.episodes_per_split is None:
            return self.episodes_per_task
        return max(self.episodes_per_task, -(-self.episodes_per_split // cases_in_split))


class RedeployConfig(_Strict):
    registered_model: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9_.-]+$", description="registry name; default sim2act-<campaign>"
    )
    alias: str = Field(default="champion", pattern=r"^[A-Za-z][A-Za-z0-9_-]*$",
                       description="the registry alias the champion carries (`sim2act eval --model ALIAS` finds it by)")


class BaselinesConfig(_Strict):
    """What the campaign is measured against, after its last iteration (stages.baselines)."""

    agents: list[Literal["expert", "ppo", "sac"]] = Field(
        default=[], description="expert: the noiseless scripted experts (the ceiling); ppo, sac: RL from scratch "
                                "(stable-baselines3) on the seen tasks, one agent per family")
    env_steps: int | dict[Family, int] | None = Field(  # each >= 64: _budgets_said_plainly
        default=None, description="each RL agent's training budget: one for every family, or per family ({metaworld: "
        "382023}: another run's exploration steps, so that a workspace without its million trains agents at them); "
        "default, and for a family the mapping leaves out: the environment steps the campaign's exploration took on it")
    families: list[Family] | None = Field(
        default=None, description="the families the RL agents train on: None, each with seen tasks that an agent "
        "acts in; a list, only those ([robosuite]: one family's agents, where another's rows are in already, with a "
        "budget for it alone where iterations is 0). Not part of an agent's key: a family's agent is the same either way")
    workers: PositiveInt = Field(default=2, description=(
        "RL agents trained at once, one core each; 1: one at a time, shortest first, each evaluated before the next "
        "begins (its rows hours earlier than beside a longer one; with baselines.threads for the idle cores)"))
    threads: PositiveInt = Field(default=1, description=(
        "torch threads of each RL agent's training: 1 beside other agents; with fewer agents at once than cores, "
        "more (workers 1 and threads 2 on 2 cores: SAC's step 1.4-1.6x faster, one agent's end ~40% sooner; the "
        "two side by side on one core each still step more in all, docs/bench-rl.md). Not part of an agent's key"))
    replay_size: PositiveInt = Field(
        default=50_000, description="SAC's replay buffer at most, in transitions (each keeps two frames: ~42 KB at "
        "84 px, so ~2.1 GB); a budget below it is kept whole")
    checkpoint_every: PositiveInt = Field(
        default=25_000, description="environment steps between an RL agent's resumable checkpoints: a kill loses "
        "at most these (SAC's checkpoint holds its replay buffer)")
    sac_encoder: Literal["critic", "separate"] = Field(
        default="separate", description="critic: one encoder, trained by the critic's loss and read by the actor with "
        "its gradients stopped (SAC-AE, DrQ; three encoder passes an update); separate: SB3's default, an encoder "
        "each (five passes and two backward ones). critic: 1.4-1.5x faster a step at 84 px but it learned less per "
        "environment step on a pixel probe (docs/bench-rl.md), so SB3's stays the default")
    end_on_success: bool = Field(
        default=False, description="end a training episode at its first success; default: at the horizon, as "
        "MetaWorld's and robosuite's RL benchmarks run theirs (their dense rewards pay nearly as much just short of "
        "success as at it, so ending there pays hovering more: envs/gym_env.py). true: the baselines before 2026-12-05")
    sac_target_entropy: Literal["acting", "all"] = Field(
        default="acting", description="SAC's entropy target: minus the action components the family acts on "
        "(MetaWorld's 4 of the 7: the 3 it ignores would take the entropy and leave the 4 little noise); all: SB3's "
        "default, minus all 7 (the baselines before 2026-12-05)")

    @field_validator("families")
    @classmethod
    def _families_once(cls, value: list[str] | None) -> list[str] | None:
        if value is not None and (not value or len(set(value)) < len(value)):
            raise ValueError(f"expected None (every family) or distinct families, got {value!r}")
        return value

    @field_validator("env_steps", mode="before")
    @classmethod
    def _budgets_said_plainly(cls, value: Any) -> Any:
        # the union's own error names its branches ("constrained-int"), not what was expected
        def steps(given: Any) -> bool:
            return isinstance(given, int) and not isinstance(given, bool) and given >= 64

        if value is None or steps(value):
            return value
        if value and isinstance(value, dict) and all(family in FAMILIES and steps(n) for family, n in value.items()):
            return value
        raise ValueError(f"expected a number of environment steps >= 64, or a mapping of families "
                         f"({', '.join(FAMILIES)}) to such numbers, got {value!r}")


# darker, more tinted, the camera moved further, heavier and larger objects than RandomiseConfig(); its lower
# friction changes no contact of an object of nominal friction 1 (MuJoCo takes a contact's larger: docs/evaluation.md)
SHIFTED_DOMAIN = RandomiseConfig(
    light=(0.35, 0.55), camera_shift_m=0.05, camera_rotation_deg=6.0, tint=0.4, colour_jitter=0.1,
    size=(1.1, 1.2), mass=(1.5, 2.0), friction=(0.45, 0.65),
)


class AdaptConfig(_Strict):
    """Adaptation to a shifted domain after the last iteration (stages.adapt), from the champion
    and from scratch; off while `episodes_per_task` is empty."""

    episodes_per_task: list[PositiveInt] = Field(
        default=[], description="target-domain episodes per seen task each pair of trainings (fine-tuned, scratch) "
                                "gets; []: no adaptation")
    domain: RandomiseConfig = Field(default=SHIFTED_DOMAIN, description="the shifted domain's randomisation")
    train_steps: PositiveInt = Field(default=300, description="optimiser steps each adaptation training takes (train.steps; train.batch_size each)")
    eval_episodes: PositiveInt = Field(default=10, description="evaluation episodes per seen task in the shifted domain")
    target_success: float = Field(default=0.8, gt=0, le=1, description="the success the episodes are counted to")
    tasks: list[str] = Field(
        default=[], description="task ids of the campaign's seen tasks to adapt on (a large campaign's few, e.g. "
        "[lift-red, mw-push, nav-room-red]); []: every seen task")
    seeds: PositiveInt = Field(
        default=1, description="trainings per point (train.seed 0..seeds-1 on the same episodes), pooled in the "
        "report with their spread: the results protocol asks 3")


# A campaign's largest colour jitter: two palette colours' jittered ranges stay apart below it (yellow and orange
# floors, navigation's 0.8 of the palette, differ by 0.28 in their most different channel: 0.14 would let them meet)
COLOUR_JITTER_MAX = 0.13


class CampaignConfig(_Strict):
    """A bootstrap campaign: K iterations of generate -> explore -> filter -> index -> train -> evaluate -> redeploy."""

    name: str = Field(default="default", pattern=r"^[a-z0-9][a-z0-9_-]*$", description="the campaign's name: its "
                      "rows, MLflow runs and registered model; with seed, its episodes' and trainings' seeds derive "
                      "from it")
    seed: int = Field(default=0, ge=0,
                      description="the campaign seed: each task's paraphrases, every explored and evaluated "
                      "episode, each training's initialisation and shuffling, and the RL agents draw from it")
    iterations: int = Field(default=2, ge=0, description="bootstrap iterations (`sim2act run --iterations` "
                            "continues a finished campaign to more); 0: no iteration, the baselines alone on the "
                            "campaign's tasks (baselines.agents, and baselines.env_steps for the RL agents' budgets)")
    tasks: TasksConfig = TasksConfig()
    render: RenderConfig = RenderConfig()
    randomise: RandomiseConfig = RandomiseConfig()
    explore: ExploreConfig = ExploreConfig()
    filter: FilterConfig = FilterConfig()
    train: TrainConfig = TrainConfig()
    evaluate: EvaluateConfig = EvaluateConfig()
    redeploy: RedeployConfig = RedeployConfig()
    baselines: BaselinesConfig = BaselinesConfig()
    adapt: AdaptConfig = AdaptConfig()

    @model_validator(mode="after")
    def _colours_stay_apart(self) -> CampaignConfig:
        for field, randomise in (("randomise", self.randomise), ("adapt.domain", self.adapt.domain)):
            if randomise.colour_jitter > COLOUR_JITTER_MAX:
                raise ValueError(f"{field}.colour_jitter: expected at most {COLOUR_JITTER_MAX} (two palette colours' "
                                 f"jittered ranges would meet), got {randomise.colour_jitter}")
        return self

    @model_validator(mode="after")
    def _baselines_see_enough(self) -> CampaignConfig:
        if {"ppo", "sac"} & set(self.baselines.agents) and self.render.image_size < 36:
            raise ValueError("baselines.agents: the RL baselines' image encoder (SB3's NatureCNN) needs "
                             f"render.image_size >= 36, got {self.render.image_size}")
        return self

    @model_validator(mode="after")
    def _no_iteration_measures_baselines_only(self) -> CampaignConfig:
        # without an iteration there is no policy to evaluate, no exploration to take the RL budgets from and
        # no champion to adapt: what such a campaign is for must be said in full
        if self.iterations:
            return self
        if not self.baselines.agents:
            raise ValueError("iterations: expected at least 1, or 0 with baselines.agents set (the baselines alone), "
                             "got 0 and no baselines")
        if {"ppo", "sac"} & set(self.baselines.agents) and self.baselines.env_steps is None:
            raise ValueError("baselines.env_steps: expected the RL agents' budget (a number, or one per family) "
                             "where iterations is 0 (no exploration to take it from), got none")
        if self.adapt.episodes_per_task:
            raise ValueError("adapt.episodes_per_task: expected [] where iterations is 0 (no champion to adapt), "
                             f"got {self.adapt.episodes_per_task}")
        return self

    @property
    def registered_model_name(self) -> str:
        return self.redeploy.registered_model or f"sim2act-{self.name}"


class ConfigError(Sim2ActError, ValueError):
    """A config that cannot run; its message is one line naming the field."""

    label = "config error: "


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader that refuses a key given twice in one mapping (PyYAML keeps the last one silently:
    a config with two `train:` blocks ran with the second alone)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *defaults`: merged keys may be overridden here
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                if key in seen:
                    raise yaml.constructor.ConstructorError(None, None, f"the key {key!r} is given twice",
                                                            key_node.start_mark)
                seen.add(key)
            except TypeError:  # a list or mapping as a key: YAML's own refusal, one line
                raise yaml.constructor.ConstructorError(None, None, "a key that is a list or a mapping",
                                                        key_node.start_mark) from None
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str):
    """YAML text as Python values, each mapping's keys given once (`_UniqueKeyLoader`)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)


def yaml_error_said(exc: Exception, prefix: int = 0) -> str:
    """A YAML error as one clause: what the parser found, and where (line and column, from 1), less `prefix`
    characters put before the first line (`--set`'s "value: ")."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or exc.__class__.__name__
    if mark is None:
        return problem
    column = mark.column + 1 - (prefix if mark.line == 0 else 0)
    return f"{problem}, line {mark.line + 1} column {max(column, 1)}"


def _read_yaml(text: str, origin: str, prefix: int = 0) -> dict[str, Any]:
    try:
        data = load_yaml(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{origin}: not valid YAML ({yaml_error_said(exc, prefix)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{origin}: the top level must be a mapping of config fields")
    return data


def preset_dict(preset: str) -> dict[str, Any]:
    if preset not in PRESETS:
        raise ConfigError(f"preset: unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    text = resources.files("schemas").joinpath(f"presets/{preset}.yaml").read_text()
    return _read_yaml(text, f"preset {preset}")


def describe_validation_error(exc: ValidationError) -> str:
    """One line per config: 'field.path: what is wrong' for the first error (and a count of the rest)."""
    errors = exc.errors()
    first = errors[0]
    field = ".".join(str(part) for part in first["loc"])
    message = "unknown key" if first["type"] == "extra_forbidden" else first["msg"].removeprefix("Value error, ")
    given = first.get("input")
    shown = not isinstance(given, dict) or len(repr(given)) <= 80  # a short mapping where a value goes, not a section
    if first["type"] not in ("extra_forbidden", "missing", "value_error") and shown:
        message += f" (got {given!r})"
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{field}: {message}{more}" if field else f"{message}{more}"  # the whole config's checks name their fields


def parse_settings(settings: list[str]) -> dict[str, Any]:
    """`--set train.contrastive_weight=0 tasks.colours=[red,blue]` -> nested overrides; each value
    is read as YAML (numbers, booleans, lists), the dotted path names the field."""
    overrides: dict[str, Any] = {}
    for setting in settings:
        path, sep, text = setting.partition("=")
        if not sep or not path:
            raise ConfigError(f"--set: {setting!r} is not FIELD.PATH=VALUE")
        *parents, leaf = path.split(".")
        if not all(path.split(".")):
            raise ConfigError(f"--set: {setting!r}: expected FIELD.PATH=VALUE with no empty part in {path!r}")
        target = overrides
        for depth, part in enumerate(parents, start=1):
            target = target.setdefault(part, {})
            if not isinstance(target, dict):  # `--set train=1 --set train.lr=2`: train is a value, not a section
                raise ConfigError(f"--set {path}: {'.'.join(parents[:depth])} was set to {target!r} by an earlier "
                                  "--set; expected a section to set a field of")
        target[leaf] = _read_yaml(f"value: {text}", f"--set {path}", prefix=len("value: "))["value"]
    return overrides


def read_text_file(path: Path, flag: str) -> str:
    """A YAML file's text; one that is not UTF-8 (a Latin-1 "café") is refused naming the file and where."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{flag}: {path} is not UTF-8 text (byte {exc.object[exc.start]:#x} at offset {exc.start}); "
                          "save it as UTF-8") from None


def load_config(
    preset: str = "default", config_file: Path | None = None, overrides: dict[str, Any] | None = None
) -> CampaignConfig:
    """Preset, then the user's YAML file on top, then command-line overrides; validated once."""
    data = preset_dict(preset)
    if config_file is not None:
        if not config_file.is_file():
            raise ConfigError(f"--config: expected a YAML file, got {'the folder ' if config_file.is_dir() else 'no such file '}"
                              f"{config_file}")
        data = deep_merge(data, _read_yaml(read_text_file(config_file, "--config"), str(config_file)))
    data = deep_merge(data, overrides or {})
    try:
        return CampaignConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc)) from None
