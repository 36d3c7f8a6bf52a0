"""Which learner settings a cell runs with: the finetune section's when a trained policy is given."""

from __future__ import annotations

import dataclasses

from flgd.config.schema import CellConfig

__all__ = ["fine_tunes", "learner_settings"]


def fine_tunes(cfg: CellConfig) -> tuple[bool, str]:
    """(whether the daemon fine-tunes, why): it does when a policy is given, and trains from scratch when not."""
    if cfg.policy:
        return True, (f"policy {cfg.policy} is a trained policy: the learner fine-tunes it with the finetune "
                      "settings, and exploration continues from the training steps the policy records")
    return False, ("no policy is given: a fresh network learns from scratch with the learning settings "
                   "(exploration from step 0)")


def learner_settings(cfg: CellConfig, fine_tune: bool) -> CellConfig:
    """``cfg`` with the finetune section's learner settings in ``learning`` when ``fine_tune``, else unchanged."""
    if not fine_tune:
        return cfg
    ft = cfg.finetune
    return dataclasses.replace(cfg, learning=dataclasses.replace(
        cfg.learning, learning_rate=ft.learning_rate, updates_per_action=ft.updates_per_action,
        batchnorm=ft.batchnorm, min_replay=ft.min_replay, anchor_weight=ft.anchor_weight,
        actor_argmax=ft.actor_argmax, grasp_twins=ft.grasp_twins))
