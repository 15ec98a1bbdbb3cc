"""The cross-view-completion (CroCo pretraining) network."""

import pytest
import torch

import pointmap as pm
from pointmap.model.pretrain import CrossViewCompletion


@pytest.mark.parametrize("mask, message", [
    (torch.tensor([[True, True, False, False], [True, True, True, False]]), "same number of masked patches"),
    (torch.ones(2, 4), "bool tensor"),
    (torch.ones(2, 5, dtype=torch.bool), r"\[2, 4\]"),
])
def test_a_mask_of_uneven_rows_or_the_wrong_type_or_shape_is_refused_with_the_reason(mask, message):
    model = CrossViewCompletion(pm.PRESETS["test"])
    img1, img2 = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    with pytest.raises(pm.ShapeError, match=message):
        model(img1, img2, mask)
    pred, used = model(img1, img2, torch.tensor([[True, True, False, False], [False, True, True, False]]))
    assert pred.shape == (2, 4, 16 * 16 * 3) and used.sum().item() == 4
