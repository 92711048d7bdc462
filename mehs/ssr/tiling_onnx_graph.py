"""The ONNX graph rewriting behind :mod:`mehs.ssr.tiling_onnx` (issue 16).

:func:`means_graph` rebuilds a graph so that every global average pooling hands on a
mean given as an input, and outputs its feature map's sum over the part of the tile the
tile owns (see :mod:`mehs.ssr.tiling_onnx` for the inputs and outputs);
:func:`find_poolings` finds those poolings; :func:`pruned_graph` keeps only the nodes
some outputs need (the collecting runs, which need no spectra).
"""

from __future__ import annotations

_GIVEN, _OWNED, _CELLS = "mehs_given", "mehs_owned", "mehs_cells"


def find_poolings(model) -> list[int]:
    """Indices in ``model.graph.node`` of the global average poolings of ``model`` (an
    ``onnx.ModelProto``).

    ``GlobalAveragePool`` nodes, and ``ReduceMean`` nodes over axes ``{2, 3}`` (or
    ``{-2, -1}``) that keep their dimensions, with the axes as an attribute (opset < 18)
    or as a constant input.
    """
    from onnx import helper, numpy_helper

    consts = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    for n in model.graph.node:
        if n.op_type == "Constant":
            for a in n.attribute:
                if a.name == "value":
                    consts[n.output[0]] = numpy_helper.to_array(a.t)
    found = []
    for i, n in enumerate(model.graph.node):
        if n.domain not in ("", "ai.onnx"):
            continue
        if n.op_type == "GlobalAveragePool":
            found.append(i)
            continue
        if n.op_type != "ReduceMean":
            continue
        attrs = {a.name: helper.get_attribute_value(a) for a in n.attribute}
        if int(attrs.get("keepdims", 1)) == 0:
            continue
        axes = attrs.get("axes")
        if axes is None and len(n.input) > 1 and n.input[1] in consts:
            axes = consts[n.input[1]].ravel().tolist()
        if axes is not None and sorted(int(a) for a in axes) in ([2, 3], [-2, -1]):
            found.append(i)
    return found


def means_graph(model, input_name: str, layout: str):
    """A copy of ``model`` whose global average poolings take given means and report
    their owned sums (see the module notes), or ``None`` when it has none.

    Returns ``(graph, k)``: the new ``onnx.ModelProto`` and the number of poolings.
    """
    import copy

    from onnx import NodeProto, TensorProto, helper

    model = copy.deepcopy(model)
    g = model.graph
    poolings = set(find_poolings(model))
    if not poolings:
        return None, 0
    opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 13)
    elem = next(i.type.tensor_type.elem_type for i in g.input if i.name == input_name)
    taken = ({o for n in g.node for o in n.output} | {i.name for i in g.input}
             | {t.name for t in g.initializer})
    count = [0]

    def name(base: str) -> str:
        while True:
            count[0] += 1
            cand = f"mehs/{base}_{count[0]}"
            if cand not in taken:
                taken.add(cand)
                return cand

    def node(op: str, inputs: list[str], out: str | None = None, **attrs) -> tuple[str, object]:
        out = out or name(op)
        return out, helper.make_node(op, inputs, [out], name=name(op + "_node"), **attrs)

    def ints(values) -> tuple[str, object]:
        return node("Constant", [], value=helper.make_tensor(
            name(""), TensorProto.INT64, [len(values)], [int(v) for v in values]))

    head = []                       # nodes that need only the graph's inputs

    def add(pair) -> str:
        head.append(pair[1])
        return pair[0]

    dims = (2, 3) if layout == "NCHW" else (1, 2)
    c = {k: add(ints([k])) for k in (0, 1, 2, 3, 4)}
    one = c[1]
    axes23 = add(ints([2, 3]))
    shape_in = add(node("Shape", [input_name]))
    tile_h = add(node("Slice", [shape_in, c[dims[0]], c[dims[0] + 1]]))
    tile_w = add(node("Slice", [shape_in, c[dims[1]], c[dims[1] + 1]]))
    owned = [add(node("Slice", [_OWNED, c[i], c[i + 1]])) for i in range(4)]

    nodes, outputs, inputs = list(head), [], []
    k = 0
    for index, original in enumerate(g.node):
        n = NodeProto()
        n.CopyFrom(original)
        if index not in poolings:
            nodes.append(n)
            continue
        x, y = n.input[0], n.output[0]
        own = name("own_mean")
        n.output[0] = own
        nodes.append(n)
        mean_in = f"mehs_mean_{k}"
        inputs.append(helper.make_tensor_value_info(mean_in, elem, [1, None, 1, 1]))
        nodes.append(helper.make_node("Where", [_GIVEN, mean_in, own], [y], name=name("Where")))
        extra = []

        def emit(pair) -> str:
            extra.append(pair[1])
            return pair[0]

        shape_x = emit(node("Shape", [x]))
        cells = []
        for a, (axis, size) in enumerate(((2, tile_h), (3, tile_w))):
            m = emit(node("Slice", [shape_x, c[axis], c[axis + 1]]))
            # pixels per cell of the map: given (learnt from earlier tiles, for a last tile
            # the network padded inside), else ceil(tile / map)
            ceil = emit(node("Div", [emit(node("Sub", [emit(node("Add", [size, m])), one])),
                                     m]))
            at = [emit(ints([2 * k + a])), emit(ints([2 * k + a + 1]))]
            given = emit(node("Slice", [_CELLS, *at]))
            cells.append(emit(node("Where", [emit(node("Greater", [given, c[0]])), given,
                                             ceil])))
        starts = emit(node("Concat", [emit(node("Div", [owned[0], cells[0]])),
                                      emit(node("Div", [owned[2], cells[1]]))], axis=0))
        ends = emit(node("Concat", [emit(node("Div", [owned[1], cells[0]])),
                                    emit(node("Div", [owned[3], cells[1]]))], axis=0))
        part = emit(node("Slice", [x, starts, ends, axes23]))
        # float16 maps summed in float32 (a sum overflows half floats)
        part32 = part if elem == TensorProto.FLOAT else emit(node("Cast", [part],
                                                                   to=TensorProto.FLOAT))
        sum_out, map_out = f"mehs_sum_{k}", f"mehs_map_{k}"
        if opset >= 13:
            emit(node("ReduceSum", [part32, axes23], sum_out, keepdims=0))
        else:
            emit(node("ReduceSum", [part32], sum_out, axes=[2, 3], keepdims=0))
        emit(node("Identity", [shape_x], map_out))
        nodes.extend(extra)
        outputs += [helper.make_tensor_value_info(sum_out, TensorProto.FLOAT, [1, None]),
                    helper.make_tensor_value_info(map_out, TensorProto.INT64, [4])]
        k += 1
    del g.node[:]
    g.node.extend(nodes)
    g.input.extend([helper.make_tensor_value_info(_GIVEN, TensorProto.BOOL, []),
                    helper.make_tensor_value_info(_OWNED, TensorProto.INT64, [4]),
                    helper.make_tensor_value_info(_CELLS, TensorProto.INT64, [2 * k])] + inputs)
    g.output.extend(outputs)
    return model, k


def pruned_graph(model, outputs: list[str]):
    """A copy of ``model`` with only the nodes that ``outputs`` need, and those outputs;
    ``None`` when a node holds a subgraph (its outer names are not followed here)."""
    import copy

    from onnx import AttributeProto

    g = model.graph
    if any(a.type in (AttributeProto.GRAPH, AttributeProto.GRAPHS)
           for n in g.node for a in n.attribute):
        return None
    needed, keep = set(outputs), []
    for n in reversed(g.node):
        if any(o in needed for o in n.output):
            keep.append(n)
            needed.update(i for i in n.input if i)
    out = copy.deepcopy(model)
    del out.graph.node[:]
    out.graph.node.extend(reversed(keep))
    kept_out = [o for o in out.graph.output if o.name in outputs]
    del out.graph.output[:]
    out.graph.output.extend(kept_out)
    inits = [t for t in out.graph.initializer if t.name in needed]
    del out.graph.initializer[:]
    out.graph.initializer.extend(inits)
    ins = [i for i in out.graph.input if i.name in needed]
    del out.graph.input[:]
    out.graph.input.extend(ins)
    return out
