# The ROS wheels' exported CMake targets name the Python and NumPy include
# directories of the machine that built them (/opt/python/cp311-cp311/...),
# which do not exist here. Point every imported target that names them at this
# interpreter's directories instead. Included after the find_package calls
# and before rosidl_generate_interfaces, which is what links against them.
# rosidl_generate_interfaces loads these two itself for services and actions.
find_package(action_msgs REQUIRED)
find_package(service_msgs REQUIRED)
find_package(Python3 REQUIRED COMPONENTS Interpreter Development NumPy)
get_directory_property(hdp_imported_targets IMPORTED_TARGETS)
foreach(target ${hdp_imported_targets})
  get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
  if(dirs MATCHES "/opt/python/")
    list(FILTER dirs EXCLUDE REGEX "^/opt/python/")
    list(APPEND dirs ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
    set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${dirs}")
  endif()
endforeach()
