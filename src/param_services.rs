//! The parameter services behind `ros2 param list/get/set/describe/dump`: the six
//! `rcl_interfaces` services of a ROS 2 node, served on their own thread.
//!
//! ROS 2 middlewares disagree on how a service request is matched with its reply on DDS:
//! * Fast DDS (`rmw_fastrtps_cpp`, the default RMW) and Connext put the request identity in the
//!   RTPS inline QoS (the "enhanced" RPC-over-DDS mapping);
//! * Cyclone DDS (`rmw_cyclonedds_cpp`) prefixes every request and reply payload with a 16-byte
//!   header (client id, sequence number).
//!
//! A server must speak the callers' mapping. ROS users pick their middleware with the
//! `RMW_IMPLEMENTATION` environment variable, for the CLI tools as for the nodes, so the node
//! reads it too ([`mapping_for_rmw`]); ros2-client's built-in services only speak the enhanced
//! mapping. The handlers are plain functions over [`ParameterAccess`], unit-tested without DDS.

use crate::params::specs;
use log::{info, warn};
use ros2_client::parameters::raw;
use ros2_client::qos::{Durability, History, Reliability};
use ros2_client::rcl_interfaces::{
    DescribeParametersRequest, DescribeParametersResponse, GetParameterTypesRequest,
    GetParameterTypesResponse, GetParametersRequest, GetParametersResponse, ListParametersRequest,
    ListParametersResponse, ListParametersResult, SetParametersAtomicallyResponse,
    SetParametersRequest, SetParametersResponse,
};
use ros2_client::service::{Server, ServiceMapping};
use ros2_client::{Name, Node, ParameterValue, QosProfile, ServiceTypeName};

/// The request/reply mapping to serve for the middleware named by `RMW_IMPLEMENTATION`
/// (`None` when unset): Cyclone's header mapping for `rmw_cyclonedds_cpp`, the enhanced
/// mapping otherwise (Fast DDS, the ROS 2 default, and Connext).
pub fn mapping_for_rmw(rmw_implementation: Option<&str>) -> ServiceMapping {
    match rmw_implementation {
        Some(rmw) if rmw.trim().contains("cyclonedds") => ServiceMapping::Cyclone,
        _ => ServiceMapping::Enhanced,
    }
}

/// A readable name of a mapping, for the log.
pub fn mapping_name(mapping: ServiceMapping) -> &'static str {
    match mapping {
        ServiceMapping::Basic => "basic",
        ServiceMapping::Enhanced => "enhanced (rmw_fastrtps_cpp, rmw_connextdds)",
        ServiceMapping::Cyclone => "cyclone (rmw_cyclonedds_cpp)",
    }
}

/// What the services need from the node: its declared parameters.
pub trait ParameterAccess {
    /// Current value, `None` if not declared.
    fn get(&self, name: &str) -> Option<ParameterValue>;
    /// Every declared name.
    fn names(&self) -> Vec<String>;
    /// Validates and applies one value, or says why not.
    fn set(&self, name: &str, value: ParameterValue) -> Result<(), String>;
    /// Validates several values together without applying them.
    fn validate_all(&self, changes: &[(String, ParameterValue)]) -> Result<(), String>;
}

/// `get_parameters`: values in request order, `NOT_SET` for unknown names (as rclcpp).
pub fn get_parameters(
    access: &dyn ParameterAccess,
    request: &GetParametersRequest,
) -> Vec<raw::ParameterValue> {
    request
        .names
        .iter()
        .map(|name| access.get(name).unwrap_or(ParameterValue::NotSet).into())
        .collect()
}

/// `get_parameter_types`: `rcl_interfaces/ParameterType` codes, 0 for unknown names.
pub fn get_parameter_types(
    access: &dyn ParameterAccess,
    request: &GetParameterTypesRequest,
) -> Vec<u8> {
    request
        .names
        .iter()
        .map(|name| {
            access.get(name).map_or(raw::ParameterType::NOT_SET, |v| {
                ParameterValue::to_parameter_type_raw(&v)
            })
        })
        .collect()
}

/// `set_parameters`: each value independently, one result each.
pub fn set_parameters(
    access: &dyn ParameterAccess,
    request: &SetParametersRequest,
) -> Vec<raw::SetParametersResult> {
    request
        .parameter
        .iter()
        .map(|p| {
            let value = ParameterValue::from(p.value.clone());
            access.set(&p.name, value).into()
        })
        .collect()
}

/// `set_parameters_atomically`: all values validated together, then applied, or none.
pub fn set_parameters_atomically(
    access: &dyn ParameterAccess,
    request: &SetParametersRequest,
) -> raw::SetParametersResult {
    let changes: Vec<(String, ParameterValue)> = request
        .parameter
        .iter()
        .map(|p| (p.name.clone(), ParameterValue::from(p.value.clone())))
        .collect();
    let result = access.validate_all(&changes).and_then(|()| {
        changes
            .into_iter()
            .try_for_each(|(name, value)| access.set(&name, value))
    });
    result.into()
}

/// `list_parameters` with rclcpp's semantics: without prefixes, names with fewer than
/// `depth` dots (0 = any); with prefixes, names equal to one or below `prefix.` within `depth`
/// more levels. `prefixes` of the result are the distinct namespaces of the listed names.
pub fn list_parameters(
    access: &dyn ParameterAccess,
    request: &ListParametersRequest,
) -> ListParametersResult {
    let depth = request.depth;
    let within_depth = |dots: usize| depth == 0 || (dots as u64) < depth;
    let mut result = ListParametersResult {
        names: Vec::new(),
        prefixes: Vec::new(),
    };
    for name in access.names() {
        let listed = if request.prefixes.is_empty() {
            within_depth(name.matches('.').count())
        } else {
            request.prefixes.iter().any(|prefix| {
                name == *prefix
                    || name
                        .strip_prefix(prefix.as_str())
                        .and_then(|rest| rest.strip_prefix('.'))
                        .is_some_and(|rest| within_depth(rest.matches('.').count() + 1))
            })
        };
        if listed {
            if let Some((namespace, _)) = name.rsplit_once('.') {
                if !result.prefixes.iter().any(|p| p == namespace) {
                    result.prefixes.push(namespace.to_string());
                }
            }
            result.names.push(name);
        }
    }
    result
}

/// `describe_parameters`: type, description, unit and range from the schema
/// ([`crate::params::specs`]), and whether it is read-only.
pub fn describe_parameters(
    access: &dyn ParameterAccess,
    request: &DescribeParametersRequest,
) -> Vec<raw::ParameterDescriptor> {
    let specs = specs();
    request
        .names
        .iter()
        .map(|name| {
            let value = access.get(name);
            let spec = specs.iter().find(|s| s.name == name);
            let description = match (spec, &value) {
                (Some(s), _) => s.description.to_string(),
                (None, Some(_)) => String::new(),
                (None, None) => "unknown parameter".into(),
            };
            let mut descriptor = raw::ParameterDescriptor {
                name: name.clone(),
                r#type: value.as_ref().map_or(
                    raw::ParameterType::NOT_SET,
                    ParameterValue::to_parameter_type_raw,
                ),
                description,
                additional_constraints: String::new(),
                read_only: value.is_none() || spec.is_some_and(|s| s.read_only),
                dynamic_typing: false,
                floating_point_range: Vec::new(),
                integer_range: Vec::new(),
            };
            if let Some(spec) = spec {
                describe_range(spec, &mut descriptor);
            }
            descriptor
        })
        .collect()
}

/// Unit and range into a descriptor. rcl enforces a range on `[from, to]`, so a parameter
/// where 0 means "default" reports `[0, max]` and states the gap in the constraints.
fn describe_range(spec: &crate::params::ParamSpec, d: &mut raw::ParameterDescriptor) {
    let mut constraints = Vec::new();
    if !spec.unit.is_empty() {
        constraints.push(format!("unit: {}", spec.unit));
    }
    if let Some(r) = spec.range {
        let from = if r.zero_means_default { 0.0 } else { r.min };
        if r.zero_means_default {
            constraints.push(format!("0 = default, else {}..={}", r.min, r.max));
        }
        match spec.default {
            crate::params::ParamValue::Integer(_) => d.integer_range.push(raw::IntegerRange {
                from_value: from as i64,
                to_value: r.max.min(i64::MAX as f64) as i64,
                step: 0,
            }),
            _ => d.floating_point_range.push(raw::FloatingPointRange {
                from_value: from,
                to_value: r.max,
                step: 0.0,
            }),
        }
    }
    if spec.read_only {
        constraints.push("read at start-up".into());
    }
    d.additional_constraints = constraints.join("; ");
}

/// The six servers of one node.
pub struct ParameterServices {
    mapping: ServiceMapping,
    get: Server<GetParametersRequest, GetParametersResponse>,
    get_types: Server<GetParameterTypesRequest, GetParameterTypesResponse>,
    set: Server<SetParametersRequest, SetParametersResponse>,
    set_atomically: Server<SetParametersRequest, SetParametersAtomicallyResponse>,
    list: Server<ListParametersRequest, ListParametersResponse>,
    describe: Server<DescribeParametersRequest, DescribeParametersResponse>,
}

/// QoS of the services, as ROS 2's `rmw_qos_profile_services_default`.
fn service_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability(Reliability::Reliable {
            when_full: ros2_client::qos::WhenFull::Fail,
        })
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

impl ParameterServices {
    /// Creates the servers `<node>/get_parameters` etc. on `node` (fully qualified name
    /// `fq_name`) with the request/reply `mapping`.
    pub fn create(node: &mut Node, fq_name: &str, mapping: ServiceMapping) -> Result<Self, String> {
        fn server<Req, Resp>(
            node: &mut Node,
            fq_name: &str,
            service: &str,
            type_name: &str,
            mapping: ServiceMapping,
        ) -> Result<Server<Req, Resp>, String>
        where
            Req: ros2_client::Message + Clone + 'static,
            Resp: ros2_client::Message + 'static,
        {
            let name = Name::new(fq_name, service)
                .map_err(|e| format!("invalid service name {fq_name}/{service}: {e}"))?;
            node.create_server(
                mapping,
                &name,
                &ServiceTypeName::new("rcl_interfaces", type_name),
                service_qos(),
                service_qos(),
            )
            .map_err(|e| format!("cannot create the {service} service: {e:?}"))
        }
        Ok(ParameterServices {
            mapping,
            get: server(node, fq_name, "get_parameters", "GetParameters", mapping)?,
            get_types: server(
                node,
                fq_name,
                "get_parameter_types",
                "GetParameterTypes",
                mapping,
            )?,
            set: server(node, fq_name, "set_parameters", "SetParameters", mapping)?,
            set_atomically: server(
                node,
                fq_name,
                "set_parameters_atomically",
                "SetParametersAtomically",
                mapping,
            )?,
            list: server(node, fq_name, "list_parameters", "ListParameters", mapping)?,
            describe: server(
                node,
                fq_name,
                "describe_parameters",
                "DescribeParameters",
                mapping,
            )?,
        })
    }

    /// Answers requests until the process ends (run it on its own thread).
    pub fn serve(self, access: &dyn ParameterAccess) {
        use futures::stream::{select_all, StreamExt};
        info!(
            "parameter services up, {} request mapping",
            mapping_name(self.mapping)
        );
        let mut requests = select_all(self.request_streams());
        futures::executor::block_on(async {
            while let Some(request) = requests.next().await {
                match request {
                    Ok(request) => self.answer(request, access),
                    // Most likely a client on another middleware's mapping.
                    Err(e) => warn!(
                        "undecodable parameter service request ({e}); this node serves the \
                         {} mapping: is the caller's RMW_IMPLEMENTATION the node's?",
                        mapping_name(self.mapping)
                    ),
                }
            }
        });
        warn!("parameter services stopped");
    }

    /// The requests of the six servers, each tagged with its service.
    fn request_streams(&self) -> Vec<RequestStream<'_>> {
        use futures::stream::StreamExt;
        vec![
            Box::pin(
                self.get
                    .receive_request_stream()
                    .map(|r| tag(r, Request::Get)),
            ),
            Box::pin(
                self.get_types
                    .receive_request_stream()
                    .map(|r| tag(r, Request::GetTypes)),
            ),
            Box::pin(
                self.set
                    .receive_request_stream()
                    .map(|r| tag(r, Request::Set)),
            ),
            Box::pin(
                self.set_atomically
                    .receive_request_stream()
                    .map(|r| tag(r, Request::SetAtomically)),
            ),
            Box::pin(
                self.list
                    .receive_request_stream()
                    .map(|r| tag(r, Request::List)),
            ),
            Box::pin(
                self.describe
                    .receive_request_stream()
                    .map(|r| tag(r, Request::Describe)),
            ),
        ]
    }

    /// Handles one request and sends its reply on the server it came from (a failed send is
    /// logged: the caller times out).
    fn answer(&self, request: Request, access: &dyn ParameterAccess) {
        let sent = match request {
            Request::Get(id, r) => self.get.send_response(
                id,
                GetParametersResponse {
                    values: get_parameters(access, &r),
                },
            ),
            Request::GetTypes(id, r) => self.get_types.send_response(
                id,
                GetParameterTypesResponse {
                    values: get_parameter_types(access, &r),
                },
            ),
            Request::Set(id, r) => self.set.send_response(
                id,
                SetParametersResponse {
                    results: set_parameters(access, &r),
                },
            ),
            Request::SetAtomically(id, r) => self.set_atomically.send_response(
                id,
                SetParametersAtomicallyResponse {
                    result: set_parameters_atomically(access, &r),
                },
            ),
            Request::List(id, r) => self.list.send_response(
                id,
                ListParametersResponse {
                    result: list_parameters(access, &r),
                },
            ),
            Request::Describe(id, r) => self.describe.send_response(
                id,
                DescribeParametersResponse {
                    values: describe_parameters(access, &r),
                },
            ),
        };
        if let Err(e) = sent {
            warn!("cannot send a parameter service reply: {e:?}");
        }
    }
}

/// A request to one of the six services, with the id its reply must carry.
enum Request {
    Get(ros2_client::RmwRequestId, GetParametersRequest),
    GetTypes(ros2_client::RmwRequestId, GetParameterTypesRequest),
    Set(ros2_client::RmwRequestId, SetParametersRequest),
    SetAtomically(ros2_client::RmwRequestId, SetParametersRequest),
    List(ros2_client::RmwRequestId, ListParametersRequest),
    Describe(ros2_client::RmwRequestId, DescribeParametersRequest),
}

/// A received request, or why it did not decode.
type RequestItem = Result<Request, String>;

/// One server's incoming requests, tagged with their service.
type RequestStream<'a> = std::pin::Pin<Box<dyn futures::Stream<Item = RequestItem> + 'a>>;

/// Tags a received request with its service (`wrap`), or describes the receive error.
fn tag<R, E: std::fmt::Debug>(
    result: Result<(ros2_client::RmwRequestId, R), E>,
    wrap: fn(ros2_client::RmwRequestId, R) -> Request,
) -> RequestItem {
    result
        .map(|(id, r)| wrap(id, r))
        .map_err(|e| format!("{e:?}"))
}

/// The node's parameters without DDS, with the node's validation: what the tests serve.
#[cfg(test)]
pub(crate) struct MemoryStore(pub std::sync::Mutex<crate::params::NodeParams>);

#[cfg(test)]
impl MemoryStore {
    /// Defaults with a 10 µm period.
    pub(crate) fn with_period() -> MemoryStore {
        let startup = crate::params::NodeParams::from_overrides(&[(
            "period".into(),
            crate::params::ParamValue::Double(10.0),
        )]);
        MemoryStore(std::sync::Mutex::new(
            startup.map(|s| s.params).unwrap_or_else(|e| panic!("{e}")),
        ))
    }
}

#[cfg(test)]
impl ParameterAccess for MemoryStore {
    fn get(&self, name: &str) -> Option<ParameterValue> {
        let params = self.0.lock().ok()?;
        params.values().get(name).cloned().map(Into::into)
    }
    fn names(&self) -> Vec<String> {
        self.0
            .lock()
            .map(|p| p.values().keys().cloned().collect())
            .unwrap_or_default()
    }
    fn set(&self, name: &str, value: ParameterValue) -> Result<(), String> {
        let mut params = self.0.lock().map_err(|e| e.to_string())?;
        *params = params.with(name, &value.into())?;
        Ok(())
    }
    fn validate_all(&self, changes: &[(String, ParameterValue)]) -> Result<(), String> {
        let mut params = self.0.lock().map_err(|e| e.to_string())?.clone();
        for (name, value) in changes {
            params = params.with(name, &value.clone().into())?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn store() -> MemoryStore {
        MemoryStore::with_period()
    }

    fn param(name: &str, value: ParameterValue) -> raw::Parameter {
        raw::Parameter {
            name: name.into(),
            value: value.into(),
        }
    }

    #[test]
    fn mapping_follows_rmw_implementation() {
        assert!(matches!(mapping_for_rmw(None), ServiceMapping::Enhanced));
        assert!(matches!(
            mapping_for_rmw(Some("rmw_fastrtps_cpp")),
            ServiceMapping::Enhanced
        ));
        assert!(matches!(
            mapping_for_rmw(Some("rmw_cyclonedds_cpp")),
            ServiceMapping::Cyclone
        ));
    }

    #[test]
    fn get_and_types_answer_in_request_order() {
        let s = store();
        let request = GetParametersRequest {
            names: vec!["period".into(), "nope".into(), "pattern_type".into()],
        };
        let values = get_parameters(&s, &request);
        assert_eq!(values[0].ptype, raw::ParameterType::DOUBLE);
        assert_eq!(values[0].double_value, 10.0);
        assert_eq!(values[1].ptype, raw::ParameterType::NOT_SET);
        assert_eq!(values[2].string_value, "periodic");
        let types = get_parameter_types(
            &s,
            &GetParameterTypesRequest {
                names: request.names.clone(),
            },
        );
        assert_eq!(
            types,
            vec![
                raw::ParameterType::DOUBLE,
                raw::ParameterType::NOT_SET,
                raw::ParameterType::STRING
            ]
        );
    }

    #[test]
    fn set_reports_each_result_and_atomic_set_is_all_or_nothing() {
        let s = store();
        let results = set_parameters(
            &s,
            &SetParametersRequest {
                parameter: vec![
                    param("period", ParameterValue::Double(12.0)),
                    param("period", ParameterValue::Double(-1.0)),
                ],
            },
        );
        assert!(results[0].successful);
        assert!(!results[1].successful && results[1].reason.contains("period"));
        assert_eq!(s.get("period"), Some(ParameterValue::Double(12.0)));

        let result = set_parameters_atomically(
            &s,
            &SetParametersRequest {
                parameter: vec![
                    param("period", ParameterValue::Double(20.0)),
                    param(
                        "relative_pairs",
                        ParameterValue::StringArray(vec!["3:3".into()]),
                    ),
                ],
            },
        );
        assert!(
            !result.successful && result.reason.contains("itself"),
            "{result:?}"
        );
        assert_eq!(
            s.get("period"),
            Some(ParameterValue::Double(12.0)),
            "nothing applied"
        );
        let result = set_parameters_atomically(
            &s,
            &SetParametersRequest {
                parameter: vec![
                    param("period", ParameterValue::Double(20.0)),
                    param(
                        "relative_pairs",
                        ParameterValue::StringArray(vec!["3:4".into()]),
                    ),
                ],
            },
        );
        assert!(result.successful, "{result:?}");
        assert_eq!(s.get("period"), Some(ParameterValue::Double(20.0)));
    }

    #[test]
    fn list_and_describe() {
        let s = store();
        let all = list_parameters(
            &s,
            &ListParametersRequest {
                prefixes: vec![],
                depth: 0,
            },
        );
        assert!(all.names.iter().any(|n| n == "period"));
        assert_eq!(all.names.len(), specs().len());
        let one = list_parameters(
            &s,
            &ListParametersRequest {
                prefixes: vec!["period".into()],
                depth: 0,
            },
        );
        assert_eq!(one.names, vec!["period".to_string()]);
        let described = describe_parameters(
            &s,
            &DescribeParametersRequest {
                names: vec![
                    "period".into(),
                    "nope".into(),
                    "window_size".into(),
                    "image_transport".into(),
                ],
            },
        );
        assert_eq!(described[0].r#type, raw::ParameterType::DOUBLE);
        assert!(described[0].description.contains("period"));
        assert!(!described[0].read_only);
        let range = &described[0].floating_point_range;
        assert_eq!((range[0].from_value, range[0].to_value), (0.0, 1e6));
        assert!(described[0].additional_constraints.contains("0 = default"));
        assert_eq!(described[1].r#type, raw::ParameterType::NOT_SET);
        assert!(described[1].read_only);
        let window = &described[2];
        assert_eq!(window.integer_range[0].to_value, 32_768);
        assert!(window.additional_constraints.contains("unit: px"));
        assert!(described[3].read_only);
    }
}
