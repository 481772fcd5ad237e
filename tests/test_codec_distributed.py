"""EMA codebooks under torch.distributed (gloo, 2 CPU ranks): every rank keeps identical codes."""

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from gesture.codec.quantizer import ResidualVectorQuantizer


def _rank_main(rank: int, workdir: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{workdir}/init", rank=rank, world_size=2)
    try:
        torch.manual_seed(0)
        rvq = ResidualVectorQuantizer(
            dim=6,
            codebook_dim=4,
            n_q=3,
            codebook_size=16,
            kmeans_iters=3,
            dead_code_every_steps=2,
            quantizer_dropout=True,
        ).train()
        data = torch.Generator().manual_seed(100 + rank)  # each rank sees different latents
        used = []
        for _ in range(7):
            used.append(rvq(torch.randn(2, 6, 8, generator=data) * (1 + rank)).codes.shape[1])
        state = {k: v.clone() for k, v in rvq.state_dict().items() if "_codebook" in k}
        gathered = [None, None]
        dist.all_gather_object(gathered, (state, used))
        if rank == 0:
            torch.save(gathered, f"{workdir}/gathered.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow  # spawns two processes (about 20 s here)
def test_codebooks_stay_identical_across_ranks(tmp_path):
    mp.start_processes(_rank_main, args=(str(tmp_path),), nprocs=2, start_method="spawn")
    (state0, used0), (state1, used1) = torch.load(tmp_path / "gathered.pt")
    assert used0 == used1  # the same quantizer-dropout draws
    assert state0.keys() == state1.keys() and len(state0) == 9
    for key in state0:
        assert torch.equal(state0[key], state1[key]), key
    assert all(float(state0[f"vq.layers.{i}._codebook._initialized"]) == 1.0 for i in range(3))
