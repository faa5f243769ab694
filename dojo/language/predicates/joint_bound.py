"""joint_at_least(object/joint, v) and joint_at_most(object/joint, v): an articulated joint's position against a
bound. Two words, one node: they differ only in the direction of the comparison."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import PredicateWord, ref_and_number, register


@dataclass(frozen=True)
class JointBound:
    joint: int
    value: float
    at_least: bool


def _compiler(at_least: bool):
    def compile_bound(ctx, arg, ref, bound) -> JointBound:
        return JointBound(ctx.joint(ref(arg[0])), float(arg[1]), at_least)
    return compile_bound


def evaluate_bound(ev, node: JointBound):
    q = ev.state["qpos"][:, node.joint]
    return (P.joint_at_least if node.at_least else P.joint_at_most)(ev.xp, q, node.value)


register(PredicateWord("joint_at_least",
                       ref_and_number("[object/joint, value]: an articulated joint's position is at least value."),
                       _compiler(True), JointBound, evaluate_bound))
register(PredicateWord("joint_at_most",
                       ref_and_number("[object/joint, value]: an articulated joint's position is at most value."),
                       _compiler(False)))
