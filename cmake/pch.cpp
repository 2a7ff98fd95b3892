// Compiled only to produce the precompiled headers every target reuses (cmake/pch.cmake).
