"""One-off, for when GRaF's half of sweeps/cross_scene_matrix_paper_recipe and sweeps/neighbor_count_paper_recipe exist:
point the matrix and neighbour-count claims of conf/claims.yaml at those records (the budgets validated on the matrix
job's own recipe), and keep the records at regime (d)'s budgets as `_budgets_d` variants of each claim.  Then run
graf-claims.  From the repository's root: python scripts/records/claims_recipe_2026_12.py"""

import re

p = "src/graf/conf/claims.yaml"
s = open(p).read()
D_VARIANT = "At the budgets read mid-schedule (GRaF 1,000 steps, KNN-DL 3,000)"
D_REASON = (
    "the same claim on the record made at the budgets read off checkpoints inside one 10,000-step schedule "
    "on two training scenes (GRaF 1,000 steps, KNN-DL 3,000): they validated another recipe than the matrix "
    "job trains; kept beside the re-run at the budgets validated on the matrix job's own recipe"
)
ids = [
    "cross_scene_vs_knn_dl",
    "cross_scene_vs_knn",
    "table5_L2_to_L4",
    "table5_plateau",
    "target_matrix_margin",
    "target_matrix_share",
]
entries = re.split(r"(?m)^(?=  - )", s)
out = []
for e in entries:
    m = re.search(r"(?m)^    id: (\w+)$", e) or re.search(r"(?m)^  - id: (\w+)$", e)
    cid = m.group(1) if m else None
    if cid in ids:
        old = e
        anchor = re.search(r"^  - &(\w+)", e).group(1)
        title = re.search(r'(?m)^    title: "(.*)"$', e).group(1)
        rec = re.search(r"(?m)^    record: (\S+)$", e).group(1)
        cmd = re.search(r'(?m)^    command: "(.*)"$', e).group(1)
        new = e.replace("sweeps/cross_scene_matrix_paper_val", "sweeps/cross_scene_matrix_paper_recipe")
        new = new.replace("sweeps/neighbor_count_paper_val", "sweeps/neighbor_count_paper_recipe")
        new = new.replace("study_steps=<1000 | 3000>", "study_steps=<1000 | 300>")
        new = new.replace(
            "(GRaF 1,000 steps, KNN-DL 3,000)", "(GRaF 1,000 steps, KNN-DL 300, each validated on the recipe it trains)"
        )
        out.append(new)
        variant = "".join(
            [
                f"  - <<: *{anchor}\n",
                f"    id: {cid}_budgets_d\n",
                f"    of: {cid}  # a re-run of that claim: a row inside its section\n",
                f'    variant: "{D_VARIANT}"\n',
                f'    title: "{title} (budgets read mid-schedule: GRaF 1,000 steps, KNN-DL 3,000)"\n',
                f'    record: {rec}\n    reason: "{D_REASON}"\n    command: "{cmd}"\n',
            ]
        )
        out.append(variant)
    else:
        out.append(e)
open(p, "w").write("".join(out))
