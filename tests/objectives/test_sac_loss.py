"""``maniskill_torchrl.objectives.SACLoss``: TorchRL's SACLoss with RLPD's ``backup_entropy``. ``False`` must give
TorchRL's own target with the entropy term at zero, whatever alpha is, and leave the actor and alpha losses as
TorchRL computes them. Small MLPs on random batches: the loss's arithmetic, which no env step adds to."""

from __future__ import annotations

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.data import Bounded
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss as TorchRLSACLoss

from maniskill_torchrl.configs import SACBackupEntropyLossConfig
from maniskill_torchrl.objectives import SACLoss

OBS, ACT, N = 5, 3, 16


def _modules():
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, (ACT,))
    net = torch.nn.Sequential(MLP(in_features=OBS, out_features=2 * ACT, num_cells=[16]), NormalParamExtractor())
    actor = ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        spec=spec,
    )
    qvalue = ValueOperator(
        MLP(in_features=OBS + ACT, out_features=1, num_cells=[16]), in_keys=["observation", "action"]
    )
    return actor, qvalue, spec


def _batch():
    g = torch.Generator().manual_seed(1)
    return TensorDict(
        {
            "observation": torch.randn(N, OBS, generator=g),
            "action": torch.rand(N, ACT, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(N, OBS, generator=g),
                "reward": (torch.rand(N, 1, generator=g) > 0.5).float(),
                "done": torch.zeros(N, 1, dtype=torch.bool),
                "terminated": torch.zeros(N, 1, dtype=torch.bool),
            },
        },
        [N],
    )


def _loss(cls, log_alpha, **kwargs):
    actor, qvalue, spec = _modules()
    loss = cls(actor, qvalue, action_spec=spec, **kwargs)
    loss.make_value_estimator(gamma=0.9)
    loss.log_alpha.data.fill_(log_alpha)
    return loss


def _target(loss, td):
    torch.manual_seed(2)  # the same next actions for every loss
    return loss._compute_target_v2(td)


def _losses(loss, td):
    torch.manual_seed(3)
    return loss(td.clone())


@pytest.mark.parametrize("log_alpha", [-1.0, 0.0, 2.0])
def test_without_entropy_backup_the_target_is_torchrls_at_alpha_zero(log_alpha):
    td = _batch()
    ours = _target(_loss(SACLoss, log_alpha, backup_entropy=False), td)
    # exp(-1e4) == 0 in float32: TorchRL's target with no entropy term
    reference = _target(_loss(TorchRLSACLoss, -1e4), td)
    torch.testing.assert_close(ours, reference, rtol=0, atol=0)
    # ...where TorchRL's target at this alpha differs: the switch has something to remove
    assert not torch.allclose(_target(_loss(TorchRLSACLoss, log_alpha), td), reference)


@pytest.mark.parametrize("log_alpha", [-1.0, 2.0])
def test_backup_entropy_true_is_torchrls_loss(log_alpha):
    td = _batch()
    ours = _losses(_loss(SACLoss, log_alpha, backup_entropy=True), td)
    theirs = _losses(_loss(TorchRLSACLoss, log_alpha), td)
    for key in ("loss_actor", "loss_qvalue", "loss_alpha"):
        torch.testing.assert_close(ours[key], theirs[key], rtol=0, atol=0)


def test_without_entropy_backup_only_the_critic_loss_changes():
    td = _batch()
    ours = _losses(_loss(SACLoss, 1.0, backup_entropy=False), td)
    theirs = _losses(_loss(TorchRLSACLoss, 1.0), td)
    for key in ("loss_actor", "loss_alpha", "alpha"):
        torch.testing.assert_close(ours[key], theirs[key], rtol=0, atol=0)
    assert not torch.allclose(ours["loss_qvalue"], theirs["loss_qvalue"])


def test_config_node_builds_the_loss():
    actor, qvalue, _ = _modules()
    cfg = OmegaConf.structured(SACBackupEntropyLossConfig(backup_entropy=False, gamma=0.9, target_entropy=-1.5))
    loss = instantiate(cfg, actor_network=actor, qvalue_network=qvalue)
    assert type(loss) is SACLoss and loss.backup_entropy is False
    assert loss.target_entropy.item() == -1.5 and loss.value_estimator.gamma.item() == pytest.approx(0.9)


def test_config_node_refuses_discrete_actions():
    actor, qvalue, _ = _modules()
    cfg = OmegaConf.structured(SACBackupEntropyLossConfig(discrete=True))
    with pytest.raises(Exception, match="continuous SACLoss"):
        instantiate(cfg, actor_network=actor, qvalue_network=qvalue)
