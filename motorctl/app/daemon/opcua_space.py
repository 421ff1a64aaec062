"""The OPC UA server's address space, built from OPC 40502's facts
(:mod:`motorctl.app.daemon.opcua_nodeset`; docs/opcua.md).

The types are made with the NodeSet's NodeIds, BrowseNames and hierarchy, and each carries its
instance declarations (OPC 10000-3 6.3: the children with their DataType, type definition,
EngineeringUnits, EURange and ModellingRule). The objects are then made from the types by
asyncua's own instantiation (``add_object(..., objecttype=...)``, OPC 10000-3 6.4: every
Mandatory child and the served Optional ones, each with a string NodeId that extends its
parent's: ``ns=2;s=CncInterface.CncAxisList.X.PosDirect.ActPos``), so the objects carry exactly
what their types declare. The figures of motorctl's own (``FollowingError``, ``Phase``, ...) are
added beside them, as plain BaseDataVariables.

:class:`Space` keeps every variable by its key (its string NodeId) for the writes of
:mod:`motorctl.app.daemon.opcua_values`.
"""

from __future__ import annotations

import datetime as _dt
import math

from motorctl.app.daemon.opcua_nodeset import (CNC_CHILDREN, CNC_ENUMS, CNC_OBJECT_TYPES, CNC_POSITION_CHILDREN,
                                               CNC_POSITION_DATA_TYPE, CNC_POSITION_VARIABLE_TYPE, EU_METRE,
                                               EU_METRE_PER_SECOND, EU_SECOND, UNECE_NS)

#: the keys' prefixes: the interface, an axis (``AXES + name``), the channel
IFACE = "CncInterface"
AXES = "CncInterface.CncAxisList."
CHANNEL = "CncInterface.CncChannelList.CncChannel"
#: the type chain of each object made (its own type first)
TYPE_CHAIN = {"CncInterfaceType": ("CncInterfaceType",), "CncAxisType": ("CncAxisType", "CncDriveType"),
              "CncChannelType": ("CncChannelType",)}
#: the EngineeringUnits of motorctl's own figures by BrowseName
EXTRA_UNITS = {"ActPos": EU_METRE, "CmdPos": EU_METRE, "FollowingError": EU_METRE,
               "ActSpeed": EU_METRE_PER_SECOND, "CmdSpeed": EU_METRE_PER_SECOND, "LoopTime": EU_SECOND,
               "TimeLeft": EU_SECOND}


def variant_type(datatype: str):
    """The VariantType of a facts DataType (an enumeration's is Int32; ``X[]``: X's)."""
    from asyncua import ua
    base = datatype.removesuffix("[]")
    if base in {name for _, name, _ in CNC_ENUMS}:
        return ua.VariantType.Int32
    if base == "CncPositionDataType":
        return ua.VariantType.ExtensionObject
    return getattr(ua.VariantType, base)


def default(datatype: str):
    """A declaration's value: 0, False, "", an empty array, the null NodeId."""
    from asyncua import ua
    if datatype.endswith("[]"):
        return []
    return {"Double": 0.0, "Boolean": False, "String": "", "UInt32": 0, "NodeId": ua.NodeId(),
            "CncPositionDataType": None}.get(datatype, 0)


def eu_information(unit: tuple):
    """An EUInformation (OPC 10000-8 5.6.3) of ``(UnitId, DisplayName, Description)``."""
    from asyncua import ua
    return ua.EUInformation(NamespaceUri=UNECE_NS, UnitId=unit[0], DisplayName=ua.LocalizedText(unit[1]),
                            Description=ua.LocalizedText(unit[2]))


class Space:
    """The CNC objects on an asyncua server (``server``, the CNC namespace's index ``ns``).
    ``vars``: key -> (NodeId, VariantType) of every variable written; ``last``: key -> the
    value written last."""

    def __init__(self, server, ns: int):
        self.server, self.ns = server, ns
        self.types: dict = {}
        self.vars: dict = {}
        self.last: dict = {}

    # ------------------------------------------------------------------ types
    async def build_types(self) -> dict:
        """OPC 40502's ObjectTypes, enumerations, CncPositionDataType and CncPositionVariableType
        with their instance declarations. Returns BrowseName -> NodeId."""
        from asyncua import ua
        from asyncua.common.structures104 import new_enum, new_enum_field, new_struct, new_struct_field
        s, ns, ids = self.server, self.ns, self.types
        for num, name, sup, abstract in CNC_OBJECT_TYPES:
            base = s.nodes.base_object_type if sup == "base" else s.get_node(ua.NodeId(sup, ns))
            t = await base.add_object_type(ua.NodeId(num, ns), ua.QualifiedName(name, ns))
            if abstract:
                await t.write_attribute(ua.AttributeIds.IsAbstract, ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
            ids[name] = t.nodeid
        for num, name, values in CNC_ENUMS:
            dt = await new_enum(s, ua.NodeId(num, ns), ua.QualifiedName(name, ns), [new_enum_field(v) for v in values])
            evs = [ua.EnumValueType(Value=i, DisplayName=ua.LocalizedText(v)) for i, v in enumerate(values)]
            await dt.add_property(0, "EnumValues", ua.Variant(evs, ua.VariantType.ExtensionObject))
            ids[name] = dt.nodeid
        d = ua.VariantType.Double
        pos, _ = await new_struct(s, ua.NodeId(CNC_POSITION_DATA_TYPE, ns), ua.QualifiedName("CncPositionDataType", ns),
                                  [new_struct_field(f, d) for f in ("ActPos", "CmdPos", "RemDist")])
        ids["CncPositionDataType"] = pos.nodeid
        await s.load_data_type_definitions()             # ua.CncPositionDataType, for the values
        vt = await s.get_node(ua.NodeId(ua.ObjectIds.BaseDataVariableType)).add_variable_type(
            ua.NodeId(CNC_POSITION_VARIABLE_TYPE, ns), ua.QualifiedName("CncPositionVariableType", ns), pos.nodeid)
        ids["CncPositionVariableType"] = vt.nodeid
        await self._position_children(vt)
        for type_name, children in CNC_CHILDREN.items():
            t = s.get_node(ids[type_name])
            for child in children:
                await self._declare(t, type_name, child)
        return ids

    def datatype_id(self, datatype: str):
        """The DataType NodeId of a facts DataType."""
        from asyncua import ua
        base = datatype.removesuffix("[]")
        return self.types[base] if base in self.types else ua.NodeId(getattr(ua.ObjectIds, base))

    async def _declare(self, parent, type_name: str, child: tuple):
        """One instance declaration of a type (module docstring), with its ModellingRule."""
        from asyncua import ua
        from motorctl.app.daemon.opcua_nodeset import OPTIONAL_SERVED
        name, kind, datatype, eu = child
        nid, qn = ua.NodeId(NamespaceIndex=self.ns), ua.QualifiedName(name, self.ns)
        if kind == "object":
            node = await parent.add_object(nid, qn, objecttype=self.types[datatype])
        elif kind == "property":
            node = await parent.add_property(nid, qn, ua.Variant(default(datatype), variant_type(datatype)),
                                             datatype=self.datatype_id(datatype))
        else:
            typedef = {"item": ua.NodeId(ua.ObjectIds.DataItemType), "analog": ua.NodeId(ua.ObjectIds.AnalogItemType),
                       "position": self.types["CncPositionVariableType"]}[kind]
            node = await self._variable(parent, nid, qn, datatype, typedef)
            if kind == "analog":
                await self._ranged(node, 0, eu)
            elif kind == "position":
                await self._position_children(node)
        await node.set_modelling_rule((type_name, name) not in OPTIONAL_SERVED)
        return node

    async def _variable(self, parent, nid, qn, datatype: str, typedef=None):
        """A variable of a facts DataType (an array's ValueRank 1) and type definition
        ``typedef`` (BaseDataVariableType when None), given at its creation so that its parent's
        reference (what a Browse and asyncua's instantiation read) names it too."""
        from asyncua import ua
        item = ua.AddNodesItem()
        item.RequestedNewNodeId, item.BrowseName, item.NodeClass = nid, qn, ua.NodeClass.Variable
        item.ParentNodeId, item.ReferenceTypeId = parent.nodeid, ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = typedef or ua.NodeId(ua.ObjectIds.BaseDataVariableType)
        a = ua.VariableAttributes()
        a.DisplayName = ua.LocalizedText(qn.Name)
        a.DataType = self.datatype_id(datatype)
        a.Value = ua.Variant(default(datatype), variant_type(datatype))
        a.ValueRank = ua.ValueRank.OneDimension if datatype.endswith("[]") else ua.ValueRank.Scalar
        a.AccessLevel = a.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
        item.NodeAttributes = a
        res = (await self.server.iserver.isession.add_nodes([item]))[0]
        res.StatusCode.check()
        return self.server.get_node(res.AddedNodeId)

    async def _ranged(self, node, ns: int, eu: tuple | None) -> None:
        """The EURange (Range 0..0 until written) and EngineeringUnits (when ``eu``) properties,
        declared Mandatory, their BrowseNames in namespace ``ns``."""
        from asyncua import ua
        r = await node.add_property(ua.NodeId(NamespaceIndex=self.ns), ua.QualifiedName("EURange", ns),
                                    ua.Variant(ua.Range(0.0, 0.0), ua.VariantType.ExtensionObject),
                                    datatype=ua.NodeId(ua.ObjectIds.Range))
        await r.set_modelling_rule(True)
        if eu is not None:
            u = await node.add_property(ua.NodeId(NamespaceIndex=self.ns), ua.QualifiedName("EngineeringUnits", ns),
                                        ua.Variant(eu_information(eu), ua.VariantType.ExtensionObject),
                                        datatype=ua.NodeId(ua.ObjectIds.EUInformation))
            await u.set_modelling_rule(True)

    async def _position_children(self, node) -> None:
        """A CncPositionVariable's (or its type's) ActPos, CmdPos, RemDist [m], EngineeringUnits
        (metre: the NodeSet gives none) and EURange, all Mandatory, in the CNC namespace."""
        from asyncua import ua
        for name, kind, datatype in CNC_POSITION_CHILDREN:
            if kind == "variable":
                v = await self._variable(node, ua.NodeId(NamespaceIndex=self.ns), ua.QualifiedName(name, self.ns),
                                         datatype)
                await v.set_modelling_rule(True)
        await self._ranged(node, self.ns, EU_METRE)

    # ------------------------------------------------------------------ objects
    async def instantiate(self, parent, key: str, name: str, type_name: str):
        """An object of ``type_name`` under ``parent``, NodeId ``key``, made by asyncua from the
        type's declarations; its variables (and their positions' children) are registered by key."""
        from asyncua import ua
        node = await parent.add_object(ua.NodeId(key, self.ns), ua.QualifiedName(name, self.ns),
                                       objecttype=self.types[type_name])
        for t in TYPE_CHAIN[type_name]:
            for cname, kind, datatype, _ in CNC_CHILDREN[t]:
                if kind == "object":
                    continue
                self.register(f"{key}.{cname}", variant_type(datatype), default(datatype))
                if kind == "position":
                    for c, k, dt in CNC_POSITION_CHILDREN:
                        if k == "variable":
                            self.register(f"{key}.{cname}.{c}", variant_type(dt), default(dt))
        return node

    def register(self, key: str, vtype, value) -> None:
        from asyncua import ua
        self.vars[key] = (ua.NodeId(key, self.ns), vtype)
        self.last[key] = value

    async def extra(self, parent, path: str, name: str, value, vtype, desc: str = ""):
        """One of motorctl's own figures (a BaseDataVariable; EngineeringUnits from
        :data:`EXTRA_UNITS`) under ``parent``, key ``path.name``."""
        from asyncua import ua
        key = f"{path}.{name}"
        node = await parent.add_variable(ua.NodeId(key, self.ns), ua.QualifiedName(name, self.ns), ua.Variant(value, vtype))
        if name in EXTRA_UNITS:
            await node.add_property(0, "EngineeringUnits",
                                    ua.Variant(eu_information(EXTRA_UNITS[name]), ua.VariantType.ExtensionObject))
        if desc:
            await self.describe(key, desc)
        self.register(key, vtype, value)
        return node

    async def describe(self, key: str, desc: str) -> None:
        from asyncua import ua
        await self.server.get_node(ua.NodeId(key, self.ns)).write_attribute(
            ua.AttributeIds.Description, ua.DataValue(ua.Variant(ua.LocalizedText(desc), ua.VariantType.LocalizedText)))

    async def set_range(self, key: str, low: float, high: float) -> None:
        """The EURange of the variable ``key`` (an AnalogItem's, or a CncPositionVariable's)."""
        from asyncua import ua
        ns = self.ns if key.rsplit(".", 1)[-1].startswith(("Pos", "AnglePos")) else 0
        node = await self.server.get_node(ua.NodeId(key, self.ns)).get_child(ua.QualifiedName("EURange", ns))
        await node.write_value(ua.Variant(ua.Range(float(low), float(high)), ua.VariantType.ExtensionObject))

    # ------------------------------------------------------------------ values
    @staticmethod
    def position(act: float, cmd: float, rem: float):
        """A CncPositionDataType value (ActPos, CmdPos, RemDist [m])."""
        from asyncua import ua
        return ua.CncPositionDataType(ActPos=act, CmdPos=cmd, RemDist=rem)

    async def write(self, key: str, value, ts=None, always: bool = False) -> None:
        """Write a variable's value (SourceTimestamp ``ts``); skipped when it equals the last
        one unless ``always``."""
        from asyncua import ua
        if not always and self.last.get(key) == value and not (isinstance(value, float) and math.isnan(value)):
            return
        self.last[key] = value
        nid, vt = self.vars[key]
        dv = ua.DataValue(ua.Variant(value, vt), SourceTimestamp=ts, ServerTimestamp=_dt.datetime.now(_dt.timezone.utc))
        await self.server.write_attribute_value(nid, dv)

    async def write_bad(self, key: str, code) -> None:
        """A variable without a value: a null value with the Bad status ``code``."""
        from asyncua import ua
        self.last[key] = None
        nid, _ = self.vars[key]
        await self.server.write_attribute_value(nid, ua.DataValue(ua.Variant(), StatusCode_=ua.StatusCode(code),
                                                                  ServerTimestamp=_dt.datetime.now(_dt.timezone.utc)))


__all__ = ["Space", "IFACE", "AXES", "CHANNEL", "variant_type", "eu_information"]
