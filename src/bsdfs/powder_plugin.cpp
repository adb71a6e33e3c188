/*
 * The entry point of the plugin library powder.so: registers the `powder` BSDF in every
 * variant it was built for (the generated list powder_variants.h, CMakeLists.txt:
 * POWDER_VARIANTS), through each variant's powder_register_<variant> (powder_variant.h,
 * compiled with powder.cpp once per variant).
 */

#include <mitsuba/core/object.h>

#include <string_view>

#include "powder_variants.h"

NAMESPACE_BEGIN(mitsuba)
#define POWDER_DECLARE(v) void powder_register_##v(std::string_view, PluginRegisterFn);
POWDER_FOR_EACH_VARIANT(POWDER_DECLARE)
NAMESPACE_END(mitsuba)

extern "C" MI_EXPORT void init_plugin(std::string_view name, mitsuba::PluginRegisterFn fn) {
    using namespace mitsuba;
#define POWDER_REGISTER(v) powder_register_##v(name, fn);
    POWDER_FOR_EACH_VARIANT(POWDER_REGISTER)
}
