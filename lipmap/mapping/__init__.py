"""LiP-Map line mapping: where each step of the paper lives (paper sections of ``lipmap-paper.tex``).

Planes (Sec. 3.1 representation, Sec. 3.3 plane loss and optimization; appendix A for the reference's settings):
    plane primitives          lipmap.planes.primitives.Planes (centre, quaternion, radii x+ x- y+ y-)
    plane initialization      lipmap.planes.init.init_planes (TSDF fusion -> decimated mesh -> one plane per face)
    differentiable renderer   lipmap.planes.render.rasterize_planes (selection: select_hits; compositing:
                              composite_hits; fused Warp twin: lipmap.planes.raster_warp)
    plane loss                lipmap.planes.losses.plane_loss (2 * depth L1 + 5 * normal L1 and 1 - cos)
    optimization loop         lipmap.planes.train.optimize_planes (one view per iteration, Adam,
                              re-centring; prune and split once per epoch, or every
                              restructure_every iterations if longer: structure.prune_and_split)
    the plane step            lipmap.planes.train.fit_planes (init + optimize -> planes.h5)

Lines (Sec. 3.2 assignment, Sec. 3.3 line loss, Sec. 3.4 finalization; appendix "Global Line Merging"):
    line-to-edge assignment   lipmap.mapping.assign: line_regions (1-px regions), PlaneRaycaster (first hit),
                              best_edges (of the hit plane's 4 edges, the 2 closest in angle, then distance)
    line loss                 lipmap.mapping.losses.line_loss (D_euc + D_ort, optional group loss, robust_px)
    line term in the loop     lipmap.mapping.supervision.LineSupervision (the ``extra_loss`` of optimize_planes)
    extraction                lipmap.mapping.extract.extract_observations (edges within 1 px / 0.01 rad)
    merging                   lipmap.mapping.extract.merge_edges (per-line DBSCAN, ids propagated, PCA fit)
    tracks                    lipmap.mapping.extract.build_tracks (the paper's track builder)
    on-plane lines (ours)     lipmap.mapping.pipeline.lipmap_linemap -> _add_on_plane_lines (detections no
                              edge explains, lifted onto the planes with lipmap.lift; not in the paper)
    one line per physical     lipmap.mapping.aggregate.aggregate_linemap (ours: lines sharing detections merged,
    line (ours)               each spanning its track as LIMAP's segments do, single-image lines along a
                              tracked one absorbed; not in the paper, off in ``paper``)
    the plane step            lipmap.mapping.joint.fit_planes_with_lines (the line term -> planes.h5, stamped
                              with the code that shapes planes only)
    the mapping step          lipmap.mapping.pipeline.map_scene (lines2d.h5 -> planes.h5 -> linemap.h5)

Localization (Sec. 4.5; ours, the reference code has none):
    line query                localization.linequery.LineQuery (projection matching, or the paper's ray cast
                              of the query line's region against the planes)
    PnPL                      localization.estimate.pnpl_pose (PoseLib, points + lines)
"""
