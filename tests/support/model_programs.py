"""Language-model programs written the paper's way (../shared/docs/LLM-API.md) for scene-0553 at 3 s,
where vehicle 17 (13 m/s) has a lane to its right and vehicle 18 (8.5 m/s) follows it: the canned
replies that tests/test_llm_steering.py serves to ``ctgpp simulate``, that tests/test_paper_api.py
checks in the worker, and that scripts/loss_overhead.py times. Plain text: importing this imports
nothing of ctgpp.
"""

SCENE = "scene-0553"

# "vehicle 18 should stay at least 25 m behind vehicle 17"
STAY_BEHIND = '''
import torch


class StayBehind(GuidanceLoss):
    """The follower keeps at least gap_m behind the leader along the leader's heading."""

    def __init__(self, follower=18, leader=17, gap_m=25.0, decay_rate=0.98):
        super().__init__()
        self.follower = follower
        self.leader = leader
        self.gap_m = gap_m
        self.decay_rate = decay_rate

    def forward(self, x, data_batch, agt_mask=None):
        if agt_mask is not None:
            x = x[agt_mask]
        pos_pred = x[..., :2]  # (B, N, T, 6) -> (B, N, T, 2)
        yaw_pred = x[..., 3:4]  # (B, N, T, 1)
        pos_world, yaw_world = transform_coord_agents_to_world(pos_pred, yaw_pred, data_batch)
        pos_lead, _ = transform_coord_world_to_agent_i(pos_world, yaw_world, data_batch, self.leader)
        leader = select_agent_ind(pos_lead, self.leader)  # (N, T, 2) in the leader's frame
        follower = select_agent_ind(pos_lead, self.follower)  # (N, T, 2)
        gap = leader[..., 0] - follower[..., 0]  # (N, T) m
        weights = torch.pow(self.decay_rate, torch.arange(x.shape[2], dtype=torch.float))  # (T,)
        return torch.mean(torch.clip(self.gap_m - gap, min=0) * weights, dim=-1)  # (N,)
'''

# "vehicle 17 should change to the lane on its right"
RIGHT_LANE = '''
import torch
from ctgpp.guidance.helpers import get_current_lane_projection, get_right_lane_projection, select_agent_ind


class GentleAcceleration(GuidanceLoss):
    def __init__(self, acc_limit):
        super().__init__()
        self.acc_limit = acc_limit

    def forward(self, x, data_batch, agt_mask=None):
        acc = x[..., 4]  # (B, N, T)
        return torch.clip(torch.abs(acc) - self.acc_limit, min=0).mean(-1)  # (B, N)


class ChangeToRightLane(GuidanceLoss):
    """Vehicle 17 leaves its lane for the one on its right, the later steps weighing more."""

    def __init__(self, target_ind=17, growth=1.03, acc_limit=3.0):
        super().__init__()
        self.target_ind = target_ind
        self.growth = growth
        self.smooth = GentleAcceleration(acc_limit)

    def forward(self, x, data_batch, agt_mask=None):
        if agt_mask is not None:
            x = x[agt_mask]
        pos_pred, yaw_pred = x[..., :2], x[..., 3:4]  # (B, N, T, 2), (B, N, T, 1)
        own = get_current_lane_projection(pos_pred, yaw_pred, data_batch)  # (B, N, T, 3)
        right = get_right_lane_projection(pos_pred, yaw_pred, data_batch)  # (B, N, T, 3)
        target = select_agent_ind(right, self.target_ind)[..., :2]  # (N, T, 2)
        here = select_agent_ind(own, self.target_ind)[..., :2]
        pos = select_agent_ind(pos_pred, self.target_ind)
        weights = self.growth ** torch.arange(x.shape[2], dtype=torch.float)  # (T,)
        to_right = torch.norm(pos - target, dim=-1)  # (N, T)
        to_own = torch.norm(pos - here, dim=-1)
        lane = torch.sum((to_right - 0.2 * to_own) * weights, dim=-1) / weights.sum()  # (N,)
        return lane + select_agent_ind(self.smooth(x, data_batch), self.target_ind)  # (N,)
'''
